"""Modbus RTU servo backend on pyserial: the master transport and the :class:`~drivers.servo.interface.Motor`.

Two layers:

* :class:`ModbusRtuClient` moves frames of :mod:`drivers.servo.modbus_rtu` over any pyserial port
  (a real RS-485 adapter, a pseudo-terminal, or ``socket://`` / ``rfc2217://`` through
  :func:`serial.serial_for_url`). It keeps the 3.5-character silence before each request, reads
  exactly one reply frame (its length follows from the header), applies a response timeout and
  retries timeouts, corrupted replies and "slave busy" answers.
* :class:`ModbusMotor` is a :class:`~drivers.servo.interface.Cia402Motor` whose objects live in
  holding registers (:mod:`drivers.servo.modbus_map`). A poll thread reads statusword, position and
  velocity at ``poll_hz`` (default 200 Hz) and stamps each sample with the host time halfway between
  sending the request and receiving the reply; the half round trip is the stamp's uncertainty.

URLs (opened with ``drivers.url.open_device("motor", url)``)::

    modbus-rtu:///dev/ttyUSB0?baud=115200&parity=E&unit=1&map=drive.toml
    modbus-rtu://127.0.0.1:5020?unit=1               # RTU frames over a TCP byte stream (pyserial socket://)
    modbus-rtu+socket://127.0.0.1:5020?unit=1        # the same, spelled out
    modbus-rtu+rfc2217://10.0.0.7:4001?unit=3        # a serial device server speaking RFC 2217

Options: ``baud`` (default 115200), ``parity`` N/E/O (default E, the Modbus default 8E1),
``stopbits`` 1/2, ``unit`` 1..247 (default 1), ``map`` (TOML register map replacing the default),
``word_order`` high_first/low_first (overrides the map's), ``timeout`` response timeout in s (default
0.1), ``retries`` (default 2), ``poll_hz`` (default 200, 0 = no polling), ``counts_per_rev`` and
``gear_ratio`` (override the ``config=`` keyword: a :class:`DriveConfig` or a dict / TOML table for
:meth:`DriveConfig.from_dict`).
"""

from __future__ import annotations

import contextlib
import math
import os
import termios
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import Any

import serial

from drivers.errors import DeviceConnectionError, DeviceTimeoutError, DeviceURLError
from drivers.servo import cia402
from drivers.servo.interface import Cia402Motor, DriveConfig, FaultInfo, MotorSample, ServoError
from drivers.servo.modbus_map import ModbusMapError, RegisterEntry, RegisterMap, default_map, load_map
from drivers.servo.modbus_rtu import (
    MAX_FRAME,
    ExceptionCode,
    ModbusError,
    ModbusExceptionError,
    ModbusFrameError,
    ReadHoldingRegisters,
    ReadHoldingRegistersResponse,
    Request,
    Response,
    RtuTiming,
    WriteMultipleRegisters,
    WriteSingleRegister,
    decode_response,
    encode_request,
    response_frame_length,
)
from drivers.url import DeviceURL, register

__all__ = [
    "LinkStats",
    "ModbusMotor",
    "ModbusRtuClient",
    "ModbusTimeoutError",
    "open_url",
]

Clock = Callable[[], float]

#: granularity of the client's read deadlines (the port's read timeout)
READ_SLICE_S = 0.005


class ModbusTimeoutError(ModbusError, DeviceTimeoutError):
    """The slave did not answer (or not completely) within the response timeout."""


@dataclass
class LinkStats:
    """Counters of one client, for diagnostics and tests."""

    transactions: int = 0
    attempts: int = 0
    timeouts: int = 0
    frame_errors: int = 0
    busy: int = 0
    failures: int = 0


@dataclass(frozen=True)
class Transaction:
    """A completed request/response pair with host times of sending and of the complete reply."""

    response: Response | None
    t_sent: float
    t_received: float


class ModbusRtuClient:
    """Modbus RTU master on a pyserial port (thread-safe: one transaction at a time).

    ``timeout`` is the response timeout: the time from the end of sending until the first byte of the
    reply. Once the reply has started, the rest must follow within its wire time plus
    ``frame_slack`` (USB-serial adapters deliver in chunks a few ms apart, so the spec's 1.5-character
    inter-byte limit is not enforceable on a host; frames are delimited by their length instead).
    Before each request the client keeps the line silent for t3.5 since the last byte it saw; after a
    broadcast (unit 0, no reply) it waits ``turnaround`` (the spec suggests 100-200 ms) so that the
    slaves can act on it before the next request.
    """

    def __init__(
        self,
        port: serial.SerialBase,
        *,
        unit: int = 1,
        timing: RtuTiming | None = None,
        timeout: float = 0.1,
        retries: int = 2,
        frame_slack: float = 0.02,
        turnaround: float = 0.1,
        clock: Clock = time.monotonic,
    ) -> None:
        if not 0 <= unit <= 247:
            raise ModbusError(f"unit address must be 0..247, got {unit}")
        if not timeout > 0 or not math.isfinite(timeout):
            raise ModbusError(f"response timeout must be > 0 s, got {timeout}")
        if retries < 0:
            raise ModbusError(f"retries must be >= 0, got {retries}")
        self.port = port
        self.unit = unit
        baud = int(getattr(port, "baudrate", 0) or 115200)
        self.timing = timing or RtuTiming.for_line(
            baud, str(getattr(port, "parity", "E")), getattr(port, "stopbits", 1)
        )
        self.timeout = timeout
        self.retries = retries
        self.frame_slack = frame_slack
        self.turnaround = turnaround
        self.clock = clock
        self.stats = LinkStats()
        # Reads wait in slices of the port's own timeout against the client's deadlines: changing
        # the timeout per read would re-apply termios each time (and a pty refuses that with parity).
        if port.timeout is None or port.timeout > READ_SLICE_S:
            try:
                port.timeout = READ_SLICE_S
            except (OSError, ValueError, serial.SerialException) as exc:
                raise DeviceConnectionError(f"cannot set the read timeout of {port.name}: {exc}") from exc
        self._lock = threading.Lock()
        self._last_activity = -math.inf

    # -- public API ------------------------------------------------------------------------
    def read_registers(self, address: int, count: int) -> tuple[int, ...]:
        return self.read_registers_timed(address, count)[0]

    def read_registers_timed(self, address: int, count: int) -> tuple[tuple[int, ...], float, float]:
        """Read holding registers; also return the host times the request left and the reply arrived."""
        tx = self.execute(ReadHoldingRegisters(address, count))
        assert isinstance(tx.response, ReadHoldingRegistersResponse)
        return tx.response.values, tx.t_sent, tx.t_received

    def write_register(self, address: int, value: int) -> None:
        self.execute(WriteSingleRegister(address, value))

    def write_registers(self, address: int, values: tuple[int, ...] | list[int]) -> None:
        self.execute(WriteMultipleRegisters(address, tuple(values)))

    def execute(self, request: Request) -> Transaction:
        """Send ``request`` and return the checked reply, retrying timeouts, corrupt frames and "busy"."""
        frame = encode_request(self.unit, request)
        with self._lock:
            self.stats.transactions += 1
            last: ModbusError | None = None
            for _attempt in range(self.retries + 1):
                self.stats.attempts += 1
                try:
                    return self._transact(frame, request)
                except ModbusTimeoutError as exc:
                    self.stats.timeouts += 1
                    last = exc
                except ModbusFrameError as exc:
                    self.stats.frame_errors += 1
                    last = exc
                except ModbusExceptionError as exc:
                    if exc.code != ExceptionCode.SERVER_DEVICE_BUSY:
                        raise
                    self.stats.busy += 1
                    last = exc
            self.stats.failures += 1
            assert last is not None
            text = f"{last} (after {self.retries + 1} attempts)"
            if isinstance(last, ModbusTimeoutError):
                raise ModbusTimeoutError(text) from last
            if isinstance(last, ModbusExceptionError):
                raise last
            raise ModbusFrameError(text) from last

    def close(self) -> None:
        with contextlib.suppress(OSError, serial.SerialException):
            self.port.close()

    # -- one attempt -----------------------------------------------------------------------
    def _transact(self, frame: bytes, request: Request) -> Transaction:
        wait = self._last_activity + self.timing.t3_5 - self.clock()
        if wait > 0:
            time.sleep(wait)
        try:
            self.port.reset_input_buffer()  # a late reply to an earlier, timed-out request
            self.port.write(frame)
            self.port.flush()
        except (OSError, serial.SerialException) as exc:
            raise DeviceConnectionError(f"Modbus port {self.port.name}: write failed: {exc}") from exc
        t_sent = self.clock()
        if self.unit == 0:  # broadcast: no reply; the next request waits for the turnaround delay
            self._last_activity = t_sent + self.timing.frame_time(len(frame)) + self.turnaround
            return Transaction(None, t_sent, t_sent)
        # the reply must start within the response timeout (after our own frame is on the wire)
        deadline = t_sent + self.timing.frame_time(len(frame)) + self.timeout
        buf = self._read_into(bytearray(), 1, deadline, request)
        # once it has started, the whole frame must follow within its wire time plus the slack
        deadline = self.clock() + self.timing.frame_time(MAX_FRAME) + self.frame_slack
        while True:
            try:
                total = response_frame_length(bytes(buf))
            except ModbusFrameError:
                self._drain()
                raise
            if total is not None:
                break
            buf = self._read_into(buf, len(buf) + 1, deadline, request)
        buf = self._read_into(buf, total, deadline, request)
        t_received = self.clock()
        self._last_activity = t_received
        return Transaction(decode_response(bytes(buf), self.unit, request), t_sent, t_received)

    def _read_into(self, buf: bytearray, n: int, deadline: float, request: Request) -> bytearray:
        while len(buf) < n:
            remaining = deadline - self.clock()
            if remaining <= 0:
                self._last_activity = self.clock()
                where = f"unit {self.unit} on {self.port.name}"
                if buf:
                    raise ModbusTimeoutError(
                        f"{where}: reply to function 0x{request.function:02X} stopped after {len(buf)} of {n} bytes"
                    )
                raise ModbusTimeoutError(
                    f"{where}: no reply to function 0x{request.function:02X} within {self.timeout * 1e3:.0f} ms"
                )
            try:
                chunk = self.port.read(n - len(buf))  # returns early once n bytes are in
            except (OSError, serial.SerialException) as exc:
                raise DeviceConnectionError(f"Modbus port {self.port.name}: read failed: {exc}") from exc
            buf += chunk
        return buf

    def _drain(self) -> None:
        """Resynchronise after garbage: read until one read slice (5 ms, more than t3.5 from 9600 baud
        up) passes in silence, for at most 0.5 s."""
        end = self.clock() + 0.5
        while self.clock() < end:
            if not self.port.read(256):  # one read-slice of silence
                break
        self._last_activity = self.clock()


# --------------------------------------------------------------------------------------------
# The Motor
# --------------------------------------------------------------------------------------------
class ModbusMotor(Cia402Motor):
    """A CiA 402 servo drive on Modbus RTU (see the module docstring)."""

    #: consecutive failed polls after which the drive counts as lost (a silent drive is a fault)
    lost_after_s = 0.5

    def __init__(
        self,
        client: ModbusRtuClient,
        register_map: RegisterMap | None = None,
        config: DriveConfig | None = None,
        *,
        poll_hz: float = 200.0,
        clock: Clock | None = None,
        buffer_size: int = 65536,
        configure: bool = True,
    ) -> None:
        super().__init__(config or DriveConfig(), clock or client.clock, buffer_size)
        if not (poll_hz == 0 or 1 <= poll_hz <= 2000):
            raise ServoError(f"poll_hz must be 0 (off) or 1..2000, got {poll_hz}")
        self.client = client
        self.map = register_map or default_map()
        self.poll_hz = poll_hz
        self.poll_errors = 0
        self._cond = threading.Condition()
        self._last_poll_sent = -math.inf
        self._last_poll_sw = 0
        self._last_ok = self.clock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._closed = False
        for index in (cia402.CONTROLWORD, cia402.STATUSWORD, cia402.POSITION_ACTUAL):
            self.map.entry(index)  # the minimum any operation needs: fail early, naming the object
        if configure:
            self._configure_drive()
        if poll_hz:
            self._thread = threading.Thread(target=self._poll_loop, name=f"modbus-poll-{client.unit}", daemon=True)
            self._thread.start()

    # -- object access through the register map ---------------------------------------------
    def read_entry(self, entry: RegisterEntry) -> int:
        regs = self.client.read_registers(entry.address, entry.count)
        return self.map.decode(entry, regs)

    def _read_object(self, index: int, subindex: int = 0) -> int:
        return self.read_entry(self.map.entry(index, subindex))

    def _write_object(self, index: int, subindex: int, value: int) -> None:
        entry = self.map.entry(index, subindex)
        if not entry.writable:
            raise ModbusMapError(f"{entry.name} (0x{index:04X}.{subindex}) is read-only in the register map")
        regs = self.map.encode(entry, value)
        if len(regs) == 1:
            self.client.write_register(entry.address, regs[0])
        else:
            self.client.write_registers(entry.address, regs)  # one request: never half a 32-bit value

    def _statusword_after(self, t: float, timeout: float) -> int:
        if self._thread is None or not self._thread.is_alive():
            self._check_open()
            return self._read_object(cia402.STATUSWORD)
        deadline = self.clock() + timeout
        with self._cond:
            while self._last_poll_sent < t:
                if self._host_fault is not None:
                    raise self._host_fault.to_exception()
                remaining = deadline - self.clock()
                if remaining <= 0:
                    raise ModbusTimeoutError(
                        f"no statusword polled from unit {self.client.unit} within {timeout:.3g} s"
                    )
                self._cond.wait(min(remaining, 0.05))
            return self._last_poll_sw

    def _error_register(self) -> int:
        """0x1001 when the register map has it; many Modbus drives do not expose it (then 0)."""
        return self._read_object(cia402.ERROR_REGISTER) if (cia402.ERROR_REGISTER, 0) in self.map else 0

    def _clear_host_fault(self) -> None:
        if self._host_fault is None:
            return
        self._read_object(cia402.STATUSWORD)  # raises if the drive is still silent
        self._host_fault = None
        self._last_ok = self.clock()

    # -- sampling -------------------------------------------------------------------------------
    def poll_once(self) -> MotorSample:
        """Read statusword, position and velocity in one go and push a time-stamped sample."""
        sample_block = self.map.sample
        if sample_block is not None:
            regs, t0, t1 = self.client.read_registers_timed(sample_block.address, sample_block.count)
            values = {e.obj: v for e, v in self.map.decode_block(sample_block.address, regs).items()}
            sw = values.get((cia402.STATUSWORD, 0))
            pos = values.get((cia402.POSITION_ACTUAL, 0))
            vel = values.get((cia402.VELOCITY_ACTUAL, 0))
        else:
            sw = pos = vel = None
            t0 = t1 = math.nan
        if sw is None or pos is None:  # no usable sample block: one read per object
            t0 = self.clock()
            sw = self._read_object(cia402.STATUSWORD)
            pos = self._read_object(cia402.POSITION_ACTUAL)
            t1 = self.clock()
        if vel is None:
            vel = self._read_object(cia402.VELOCITY_ACTUAL) if (cia402.VELOCITY_ACTUAL, 0) in self.map else 0
        c = self.config
        sample = MotorSample(0.5 * (t0 + t1), c.counts_to_rad(pos), c.counts_to_rad(vel), sw)
        with self._cond:
            self._last_poll_sent = t0
            self._last_poll_sw = sw
            self._cond.notify_all()
        self._push_sample(sample)
        return sample

    def _poll_loop(self) -> None:
        period = 1.0 / self.poll_hz
        next_t = self.clock()
        while not self._stop.is_set():
            try:
                self.poll_once()
                self._last_ok = self.clock()
            except (ModbusError, DeviceConnectionError, DeviceTimeoutError) as exc:
                self.poll_errors += 1
                if self._host_fault is None and self.clock() - self._last_ok > self.lost_after_s:
                    self._host_fault = FaultInfo(
                        cia402.ERR_HEARTBEAT,
                        f"Modbus drive (unit {self.client.unit}) stopped answering: {exc}",
                        0x11,
                        self.clock(),
                        source="heartbeat",
                    )
                    with self._cond:
                        self._cond.notify_all()
            next_t += period
            delay = next_t - self.clock()
            if delay < 0:  # overrun (slow line): skip the missed slots instead of bursting
                next_t = self.clock()
                delay = 0.0
            self._stop.wait(delay)

    # -- lifetime -------------------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise DeviceConnectionError("Modbus motor is closed")

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.client.close()


# --------------------------------------------------------------------------------------------
# URL handler
# --------------------------------------------------------------------------------------------
_SUB_SCHEMES = {"socket": "socket", "rfc2217": "rfc2217"}


def _port_url(url: DeviceURL) -> str:
    scheme = url.scheme
    if scheme == "modbus-rtu":
        if url.host:  # modbus-rtu://host:port = RTU frames over a TCP byte stream, like +socket
            if url.port is None:
                raise DeviceURLError(
                    f"{url.raw!r}: modbus-rtu://HOST:PORT needs a port; a serial device takes three slashes "
                    "(modbus-rtu:///dev/ttyUSB0)"
                )
            if url.path not in ("", "/"):
                raise DeviceURLError(f"{url.raw!r}: modbus-rtu://HOST:PORT takes no path")
            return f"socket://{url.host}:{url.port}"
        if not url.path or url.path == "/":
            raise DeviceURLError(f"{url.raw!r}: no serial device path (modbus-rtu:///dev/ttyUSB0)")
        return url.path
    family, _, sub = scheme.partition("+")
    if family != "modbus-rtu" or sub not in _SUB_SCHEMES:
        raise DeviceURLError(
            f"{url.raw!r}: unknown scheme {scheme!r} (modbus-rtu, modbus-rtu+socket, modbus-rtu+rfc2217)"
        )
    if not url.host or url.port is None:
        raise DeviceURLError(f"{url.raw!r}: {scheme} needs host:port")
    if url.path not in ("", "/"):
        raise DeviceURLError(f"{url.raw!r}: {scheme} takes no path")
    return f"{_SUB_SCHEMES[sub]}://{url.host}:{url.port}"


def open_url(url: DeviceURL | str, *, config: DriveConfig | Mapping[str, Any] | None = None, clock: Clock | None = None,
             **kwargs: Any) -> ModbusMotor:  # fmt: skip
    """Open a Modbus RTU servo drive from its URL (see the module docstring for the options)."""
    if kwargs:
        raise DeviceURLError(f"open_url: unexpected keyword argument(s) {', '.join(sorted(kwargs))}")
    u = url if isinstance(url, DeviceURL) else DeviceURL.parse(url)
    port_url = _port_url(u)
    baud = u.get_int("baud", 115200, lo=300, hi=4_000_000)
    parity = u.get_str("parity", "E", choices=("N", "E", "O"))
    stopbits = u.get_int("stopbits", 1, lo=1, hi=2)
    unit = u.get_int("unit", 1, lo=1, hi=247)
    timeout = u.get_float("timeout", 0.1, lo=1e-3, hi=60.0)
    retries = u.get_int("retries", 2, lo=0, hi=20)
    poll_hz = u.get_float("poll_hz", 200.0, lo=0.0, hi=2000.0)
    map_path = u.get_str("map", "")
    word_order = u.get_str("word_order", "", choices=("", "high_first", "low_first"))
    cfg = config if isinstance(config, DriveConfig) else DriveConfig.from_dict(config or {})
    overrides: dict[str, Any] = {}
    if u.has("counts_per_rev"):
        overrides["counts_per_rev"] = u.get_int("counts_per_rev", lo=1)
    if u.has("gear_ratio"):
        overrides["gear_ratio"] = u.get_float("gear_ratio")
    u.check_all_used()
    if overrides:
        cfg = replace(cfg, **overrides)
    regmap = load_map(map_path) if map_path else default_map()
    if word_order:
        regmap = RegisterMap(regmap.entries, word_order, regmap.sample, regmap.source)  # type: ignore[arg-type]
    # A pseudo-terminal has no parity bit: Linux drops PARENB from its termios and then refuses
    # (EINVAL) to apply it again on the next open, so a pty is opened as 8N1. The parity still sets
    # the character time (11 bits for 8E1) the silent intervals are computed from.
    is_pty = port_url.startswith("/") and os.path.realpath(port_url).startswith("/dev/pts/")
    try:
        port = serial.serial_for_url(
            port_url,
            baudrate=baud,
            bytesize=serial.EIGHTBITS,
            parity="N" if is_pty else parity,
            stopbits=serial.STOPBITS_TWO if stopbits == 2 else serial.STOPBITS_ONE,
            timeout=READ_SLICE_S,
            exclusive=True if port_url.startswith("/") else None,
        )
    except (OSError, ValueError, serial.SerialException, termios.error) as exc:
        raise DeviceConnectionError(f"cannot open {port_url} for {u.raw!r}: {exc}") from exc
    timing = RtuTiming.for_line(baud, parity, stopbits)
    client = ModbusRtuClient(port, unit=unit, timing=timing, timeout=timeout, retries=retries,
                             clock=clock or time.monotonic)  # fmt: skip
    try:
        return ModbusMotor(client, regmap, cfg, poll_hz=poll_hz, clock=clock)
    except BaseException:
        client.close()
        raise


# ``modbus-rtu`` itself (device paths and host:port) is registered lazily in drivers/url.py; the
# ``+socket`` / ``+rfc2217`` spellings are registered here, so they resolve only once this module has
# been imported (any ``modbus-rtu://`` URL opened before does that).
register("motor", "modbus-rtu+", open_url)
