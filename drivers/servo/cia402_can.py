"""CANopen CiA 402 backend on python-can (with the ``canopen`` library's SDO client and NMT).

URL: ``canopen+<python-can interface>://<channel>?node=N&...``, for example
``canopen+virtual://bus1?node=1``, ``canopen+socketcand://127.0.0.1:29536/can0?node=1``,
``canopen+socketcan://can0?node=1``, ``canopen+pcan://PCAN_USBBUS1?node=1&bitrate=500000``.
For ``socketcand`` the host and port are the daemon's and the path is the CAN channel; for every
other interface the host part (or the path) is the channel. Options:

=================  =========  ====================================================================
``node``           1          CANopen node id of the drive (1..127)
``sync_hz``        200        SYNC produced by this driver (10..1000 Hz); one sample per SYNC;
                              0 = another master produces SYNC (its SYNCs are timestamped here)
``setup``          1          configure the node on open (NMT, heartbeat, PDO mapping, windows);
                              0 = join a drive another master has set up, changing nothing
``heartbeat_ms``   100        heartbeat period written to the drive's 0x1017 (0 = no watchdog;
                              with ``setup=0`` the drive's own 0x1017 is used)
``heartbeat_lost`` 5          the drive is lost after this many heartbeat periods of silence
                              (0.5 s by default: simulated drives share busy CPUs)
``master_id``      127        node id of this driver's own heartbeat (every ``heartbeat_ms``),
                              which the drive consumes (0x1016:1, same tolerance): if this
                              process dies the drive faults (0x8130) and stops; 0 = off
``sdo_timeout``    1.0        seconds to wait for each SDO response
``drive_stamp``    1          map the drive's time stamp 0x1013 into the samples when it has one
                              (0 = never: samples carry only the SYNC time); with ``setup=0``
                              the layout the other master mapped is read back and decoded
``bitrate``        (none)     passed to python-can for interfaces that need it
``counts_per_rev`` (config)   encoder counts per motor revolution, overrides the DriveConfig
``gear_ratio``     (config)   motor revolutions per output revolution, overrides the DriveConfig
=================  =========  ====================================================================

On open the driver checks 0x1000 (profile 402), puts the node in Pre-operational, sets the
heartbeat, maps the sample TPDOs (both transmission type 1, every SYNC), writes the configured
windows and limits, starts the node (Operational), and runs its own SYNC producer thread. When
the drive answers an SDO read of 0x1013 (high resolution time stamp, µs) the sample TPDOs are
TPDO1 = position actual + 0x1013 and TPDO2 = statusword + velocity actual
(:data:`cia402.SAMPLE_TPDOS_STAMPED`): every sample then carries the drive's own time of the
latch, raw (:attr:`MotorSample.drive_stamp_us`), with the host time it was received
(:attr:`MotorSample.t_rx_host_s`); mapping that clock to host time is the caller's (the service
does it with its clock model). Otherwise TPDO1 = statusword + position actual and TPDO2 =
velocity actual + following error (:data:`cia402.SAMPLE_TPDOS_PLAIN`), as before.
Every TPDO1 is stamped with the
host time of the SYNC it answers (paired first-in first-out, so a TPDO that arrives after the
next SYNC still gets its own SYNC's time; CAN keeps order and does not drop frames); that is
the sample's ``t_host_s`` in both layouts. A sample
is emitted when the matching TPDO2 arrives, and only then do waits on the statusword see it
(so a wait that returned has its sample stored).
The controlword is written by SDO (each command confirmed by the drive). The driver also
produces its own heartbeat (``master_id``) and has the drive consume it, so that a host that
dies mid-move leaves a drive that faults (0x8130) and stops. ``close()`` switches that consumer
off, stops the SYNC and the watchdog and releases the bus; it leaves the drive's state alone.

``setup=0&sync_hz=0`` is the passive way in, for a second process (``lrms motor status``) while
another master runs the drive: no NMT command, no re-mapping, no SYNC of its own; samples come
from the other master's SYNCs (assumed to use one of this driver's two PDO layouts: which one is
read from the drive's 0x1A00), and when no TPDOs flow
the statusword is read by SDO.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import socket
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, replace
from typing import Any
from urllib.parse import urlsplit

import can
import canopen
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from drivers.errors import DeviceConnectionError, DeviceTimeoutError, DeviceURLError, DriverError
from drivers.servo import cia402
from drivers.servo.interface import (
    Cia402Motor,
    Clock,
    ConnectionLost,
    DriveConfig,
    FaultInfo,
    HeartbeatLost,
    MotorSample,
    SdoAbort,
    ServoError,
    ServoValueError,
)
from drivers.url import DeviceURL

log = logging.getLogger(__name__)


class SdoTimeout(ServoError, DeviceTimeoutError):
    """The drive did not answer an SDO request in time."""


class NotCia402Device(ServoError):
    """Object 0x1000 says the node does not implement device profile 402."""


@dataclass(frozen=True)
class CanUrlOptions:
    node: int = 1
    sync_hz: float = 200.0
    setup: bool = True
    heartbeat_ms: int = 100
    heartbeat_lost: float = 5.0
    master_id: int = 127
    sdo_timeout: float = 1.0
    drive_stamp: bool = True
    counts_per_rev: int | None = None
    gear_ratio: float | None = None

    def drive_config(self, base: DriveConfig | Mapping[str, Any] | None) -> DriveConfig:
        config = base if isinstance(base, DriveConfig) else DriveConfig.from_dict(base or {})
        if self.counts_per_rev is not None:
            config = replace(config, counts_per_rev=self.counts_per_rev)
        if self.gear_ratio is not None:
            config = replace(config, gear_ratio=self.gear_ratio)
        return config


def read_url_options(url: DeviceURL) -> CanUrlOptions:
    """The driver options of a ``canopen+...://`` (or ``sim://``) URL (marks them used)."""
    return CanUrlOptions(
        node=url.get_int("node", 1, lo=1, hi=127),
        sync_hz=_sync_rate(url),
        setup=url.get_bool("setup", True),
        heartbeat_ms=url.get_int("heartbeat_ms", 100, lo=0, hi=65535),
        heartbeat_lost=url.get_float("heartbeat_lost", 5.0, lo=1.5, hi=100.0),
        master_id=url.get_int("master_id", 127, lo=0, hi=127),
        sdo_timeout=url.get_float("sdo_timeout", 1.0, lo=0.01, hi=30.0),
        drive_stamp=url.get_bool("drive_stamp", True),
        counts_per_rev=url.get_int("counts_per_rev", lo=1) if url.has("counts_per_rev") else None,
        gear_ratio=url.get_float("gear_ratio") if url.has("gear_ratio") else None,
    )


def _sync_rate(url: DeviceURL) -> float:
    rate = url.get_float("sync_hz", 200.0, lo=0.0, hi=1000.0)
    if 0.0 < rate < 10.0:
        raise DeviceURLError(f"sync_hz={rate:g} in {url.raw!r}: use 0 (no SYNC of our own) or 10..1000")
    return rate


def bus_kwargs(url: DeviceURL) -> dict[str, Any]:
    """python-can ``Bus`` keyword arguments for a ``canopen+<interface>://`` URL (marks options used)."""
    scheme = url.scheme
    if not scheme.startswith("canopen+") or scheme == "canopen+":
        raise DriverError(f"not a canopen+<interface> URL: {url.raw!r}")
    interface = scheme.split("+", 1)[1]
    if interface == "udp_multicast":
        raise DriverError("python-can's udp_multicast sends frames onto the network; it is not allowed here")
    kwargs: dict[str, Any] = {"interface": interface}
    netloc = urlsplit(url.raw).netloc  # keeps the channel's case (hostname is lower-cased)
    path = url.path.lstrip("/")
    if interface == "socketcand":
        if not url.host or url.port is None:
            raise DriverError(
                f"socketcand URL needs host:port, e.g. canopen+socketcand://127.0.0.1:29536/can0: {url.raw!r}"
            )
        kwargs.update(host=url.host, port=url.port, channel=path or "can0", tcp_tune=True)
    else:
        channel = netloc or path
        if not channel:
            raise DriverError(f"no CAN channel in {url.raw!r}")
        kwargs["channel"] = channel
    if url.has("bitrate"):
        kwargs["bitrate"] = url.get_int("bitrate", lo=1000, hi=1_000_000)
    return kwargs


def open_url(url: DeviceURL | str, **kw: Any) -> Cia402CanMotor:
    """Open ``canopen+<interface>://...`` (see the module docstring); keywords: ``config``, ``clock``."""
    parsed = url if isinstance(url, DeviceURL) else DeviceURL.parse(url)
    kwargs = bus_kwargs(parsed)
    options = read_url_options(parsed)
    parsed.check_all_used()
    return Cia402CanMotor.open_bus(kwargs, options, **kw)


def _probe_tcp(host: str, port: int, timeout: float = 2.0) -> None:
    try:
        with socket.create_connection((host, port), timeout=timeout):
            pass
    except OSError as exc:
        raise DeviceConnectionError(f"no socketcand server at {host}:{port}: {exc}") from None


class Cia402CanMotor(Cia402Motor):
    """A CiA 402 drive on a CANopen bus (see the module docstring)."""

    def __init__(
        self,
        bus: can.BusABC,
        options: CanUrlOptions | None = None,
        *,
        config: DriveConfig | Mapping[str, Any] | None = None,
        clock: Clock = time.monotonic,
        on_close: Callable[[], None] | None = None,
        buffer_size: int = 65536,
    ) -> None:
        self.options = options or CanUrlOptions()
        super().__init__(self.options.drive_config(config), clock, buffer_size)
        self.node_id = self.options.node
        self.on_close = on_close
        self.sim_node: Any = None  # set by sim:// (the simulated node behind this driver)
        self._closed = False
        self._stop = threading.Event()
        self._sdo_lock = threading.Lock()
        self._sw_cond = threading.Condition()
        self._last_sw: tuple[float, int] | None = None  # (SYNC time, statusword)
        #: the sample TPDOs' mappings (set at start-up: with or without the drive's time stamp)
        self.sample_tpdos: tuple[cia402.PdoMapping, cia402.PdoMapping] = cia402.SAMPLE_TPDOS_PLAIN
        #: the sample TPDOs' layout is settled (mapped by this driver, or read back by a passive
        #: master): until then no TPDO is decoded with a guessed layout (a drive still running in
        #: the other layout, or another master's)
        self._layout_known = False
        # (SYNC time, receive time, TPDO1's values by object index)
        self._pending_tpdo1: tuple[float, float, dict[int, int]] | None = None
        # unanswered SYNCs, oldest first; more than 0.5 s of them means answers were lost
        outstanding = max(8, round(0.5 * (self.options.sync_hz or 100.0)))
        self._sync_times: collections.deque[float] = collections.deque(maxlen=outstanding)
        #: host time of every SYNC sent (or seen, with sync_hz=0), newest last: diagnostics
        self.sync_history: collections.deque[float] = collections.deque(maxlen=4096)
        self._pair_window_start = -math.inf
        self._pair_min_backlog = 0
        self.resyncs = 0  # times a lost TPDO was detected and the pairing corrected
        #: seconds of consistently late pairing that prove a lost TPDO (not merely a slow link)
        self.pairing_window_s = 5.0
        self._sync_lock = threading.Lock()
        self._last_heartbeat: float | None = None
        self._heartbeat_ms = self.options.heartbeat_ms
        self._last_tpdo_rx: float | None = None
        self._master_heartbeat_on = False
        self._heartbeat_state: int | None = None
        self.emcy_history: collections.deque[tuple[float, cia402.Emcy]] = collections.deque(maxlen=32)
        self._emcy_callbacks: list[Callable[[float, cia402.Emcy], None]] = []
        self.sync_count = 0
        self.tpdo_count = 0

        self.network = canopen.Network(bus)
        self.node = canopen.RemoteNode(self.node_id, canopen.ObjectDictionary())
        self.node.sdo.RESPONSE_TIMEOUT = self.options.sdo_timeout
        self.node.sdo.MAX_RETRIES = 1
        self.network.add_node(self.node)
        n = self.node_id
        self.network.subscribe(0x180 + n, self._on_tpdo1)
        self.network.subscribe(0x280 + n, self._on_tpdo2)
        self.network.subscribe(0x700 + n, self._on_heartbeat)
        self.network.subscribe(0x080 + n, self._on_emcy)
        if not self.options.sync_hz:
            self.network.subscribe(0x080, self._on_sync_seen)
        self.network.connect()
        self._sync_thread: threading.Thread | None = None
        try:
            self._start_node()
        except BaseException:
            self.close()
            raise

    @classmethod
    def open_bus(
        cls,
        kwargs: Mapping[str, Any],
        options: CanUrlOptions,
        **kw: Any,
    ) -> Cia402CanMotor:
        """Create the python-can bus from ``kwargs`` and open the drive on it (the motor owns the bus)."""
        kwargs = dict(kwargs)
        if kwargs.get("interface") == "socketcand":
            _probe_tcp(kwargs["host"], kwargs["port"])
        try:
            bus = can.Bus(**kwargs)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise DeviceConnectionError(f"cannot open CAN bus {kwargs}: {exc}") from exc
        return cls(bus, options, **kw)

    # ------------------------------------------------------------------------------------------
    # start-up
    # ------------------------------------------------------------------------------------------
    def _start_node(self) -> None:
        device_type = self._read_object(cia402.DEVICE_TYPE)
        if device_type & 0xFFFF != 402:
            raise NotCia402Device(f"node {self.node_id}: device type 0x{device_type:08X} is not a CiA 402 drive")
        if self.options.setup:
            self._nmt(0x80)  # Pre-operational: PDO mapping may change
            self._write_object(cia402.PRODUCER_HEARTBEAT_TIME, 0, self.options.heartbeat_ms)
            if self.options.drive_stamp and self._has_time_stamp():
                self.sample_tpdos = cia402.SAMPLE_TPDOS_STAMPED
            for k, mapping in enumerate(self.sample_tpdos):
                self._map_tpdo(k, list(mapping))
            self._layout_known = True
            self._write_object(cia402.SYNC_COUNTER_OVERFLOW, 0, 0)
            self._configure_drive()
            self._setup_master_heartbeat()
            self._nmt(0x01)  # Operational
        else:
            self._heartbeat_ms = self._read_object(cia402.PRODUCER_HEARTBEAT_TIME)
            # decode what the other master mapped, whatever drive_stamp says (it only chooses the
            # layout this driver maps itself, with setup=1)
            if self._read_tpdo_mapping(0) == cia402.SAMPLE_TPDOS_STAMPED[0]:
                self.sample_tpdos = cia402.SAMPLE_TPDOS_STAMPED
            self._layout_known = True
        self._controlword = self._read_object(cia402.CONTROLWORD)
        if self._heartbeat_ms:
            self._last_heartbeat = self.clock()  # the watchdog starts now
        self._sync_thread = threading.Thread(target=self._sync_loop, name=f"canopen-sync-{self.node_id}", daemon=True)
        self._sync_thread.start()
        if self.options.sync_hz:  # first TPDO: the node is up and answering our SYNC
            with self._sw_cond:
                self._sw_cond.wait_for(lambda: self._last_sw is not None, timeout=1.0)

    def _has_time_stamp(self) -> bool:
        """The drive has object 0x1013 (an SDO read of it succeeds)."""
        try:
            self._read_object(cia402.HIGH_RES_TIMESTAMP)
        except SdoAbort as exc:
            log.info("node %d: no time stamp 0x1013 (%s): samples carry the SYNC time only", self.node_id, exc)
            return False
        return True

    @property
    def drive_stamped(self) -> bool:
        """The samples carry the drive's own latch time (0x1013 mapped next to the position)."""
        return self.sample_tpdos == cia402.SAMPLE_TPDOS_STAMPED

    def _read_tpdo_mapping(self, k: int) -> cia402.PdoMapping | None:
        """TPDO k+1's mapping as the drive holds it (None if the drive refuses to tell)."""
        try:
            n = self._read_object(cia402.TPDO_MAP + k, 0)
            return tuple(
                cia402.split_pdo_map_entry(self._read_object(cia402.TPDO_MAP + k, sub)) for sub in range(1, n + 1)
            )
        except SdoAbort:
            return None

    def _setup_master_heartbeat(self) -> None:
        """Let the drive watch this driver's heartbeat (0x1016:1), so a dead host stops the motor."""
        o = self.options
        if not o.master_id or not o.heartbeat_ms:
            return
        if o.master_id == self.node_id:
            raise DeviceURLError(f"master_id {o.master_id} is the drive's own node id")
        consumer_ms = min(0xFFFF, round(o.heartbeat_lost * o.heartbeat_ms))
        self._send_master_heartbeat()  # before the drive starts watching
        try:
            self._write_object(cia402.CONSUMER_HEARTBEAT_TIME, 1, (o.master_id << 16) | consumer_ms)
        except SdoAbort as exc:  # a drive without a heartbeat consumer: carry on without
            log.warning("node %d: no heartbeat consumer (%s); a dead host will not stop it", self.node_id, exc)
            return
        self._master_heartbeat_on = True

    def _send_master_heartbeat(self) -> None:
        try:
            self.network.send_message(0x700 + self.options.master_id, bytes([0x05]))
        except (can.CanError, OSError, RuntimeError) as exc:
            log.debug("node %d: master heartbeat not sent: %s", self.node_id, exc)

    def _nmt(self, command: int) -> None:
        self.network.send_message(0x000, bytes([command, self.node_id]))

    def _map_tpdo(self, k: int, entries: list[tuple[int, int, int]]) -> None:
        """Re-map TPDO k+1 by the CiA 301 procedure (invalidate, clear, entries, count, type, validate)."""
        comm, mapping = cia402.TPDO_COMM + k, cia402.TPDO_MAP + k
        cob = (0x180 + 0x100 * k + self.node_id) | (1 << 30)  # no RTR
        self._write_object(comm, 1, cob | (1 << 31))
        self._write_object(mapping, 0, 0)
        for sub, (index, subindex, bits) in enumerate(entries, start=1):
            self._write_object(mapping, sub, cia402.pdo_map_entry(index, subindex, bits))
        self._write_object(mapping, 0, len(entries))
        self._write_object(comm, 2, 1)  # synchronous, every SYNC
        self._write_object(comm, 1, cob)

    # ------------------------------------------------------------------------------------------
    # SDO
    # ------------------------------------------------------------------------------------------
    @contextlib.contextmanager
    def _sdo_transfer(self, index: int, subindex: int) -> Iterator[None]:
        """One SDO transfer at a time; canopen's and the bus's exceptions become this package's errors."""
        with self._sdo_lock:
            try:
                yield
            except SdoAbortedError as exc:
                raise SdoAbort(index, subindex, exc.code) from None
            except SdoCommunicationError as exc:
                raise SdoTimeout(
                    f"node {self.node_id}: no SDO answer for 0x{index:04X}:{subindex:02X} ({exc})"
                ) from None
            except (can.CanError, OSError) as exc:
                raise DeviceConnectionError(f"CAN send failed: {exc}") from exc

    def sdo_upload(self, index: int, subindex: int = 0) -> bytes:
        """Read any object's raw bytes (expedited or segmented upload)."""
        with self._sdo_transfer(index, subindex):
            data: bytes = self.node.sdo.upload(index, subindex)
            return data

    def sdo_download(self, index: int, subindex: int, data: bytes, *, force_segment: bool = False) -> None:
        """Write any object's raw bytes (expedited when <= 4 bytes unless ``force_segment``)."""
        with self._sdo_transfer(index, subindex):
            self.node.sdo.download(index, subindex, data, force_segment=force_segment)

    def _read_object(self, index: int, subindex: int = 0) -> int:
        spec = cia402.object_spec(index, subindex)
        data = self.sdo_upload(index, subindex)
        if len(data) < spec.dtype.size:
            raise ServoError(f"0x{index:04X}:{subindex:02X}: drive sent {len(data)} bytes for a {spec.dtype.name}")
        return spec.dtype.decode(data[: spec.dtype.size])

    def _write_object(self, index: int, subindex: int, value: int) -> None:
        spec = cia402.object_spec(index, subindex)
        lo, hi = spec.dtype.range
        if not lo <= value <= hi:
            raise ServoValueError(f"0x{index:04X}:{subindex:02X} {spec.name}: {value} outside [{lo}, {hi}]")
        self.sdo_download(index, subindex, spec.dtype.encode(value))

    # ------------------------------------------------------------------------------------------
    # SYNC, TPDOs, heartbeat, EMCY
    # ------------------------------------------------------------------------------------------
    def _on_sync_seen(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """Another master's SYNC (``sync_hz=0``): stamp it on arrival."""
        with self._sync_lock:
            t = self.clock()
            self._sync_times.append(t)
            self.sync_history.append(t)

    def _sync_loop(self) -> None:
        if not self.options.sync_hz:  # SYNC comes from elsewhere: only watch
            hb_period = self.options.heartbeat_ms / 1000.0
            next_hb = time.monotonic()
            while not self._stop.wait(0.01):
                if self._master_heartbeat_on and time.monotonic() >= next_hb:
                    self._send_master_heartbeat()
                    next_hb = time.monotonic() + hb_period
                self._watchdog()
            return
        period = 1.0 / self.options.sync_hz
        next_t = time.monotonic()
        failing = False
        hb_period = self.options.heartbeat_ms / 1000.0
        next_hb = next_t
        while not self._stop.is_set():
            delay = next_t - time.monotonic()
            if delay > 0 and self._stop.wait(delay):
                break
            t_sync = self.clock()
            with self._sync_lock:
                self._sync_times.append(t_sync)
                self.sync_history.append(t_sync)
            try:
                self.network.send_message(0x080, b"")
                self.sync_count += 1
                failing = False
            except (can.CanError, OSError, RuntimeError) as exc:
                if self._stop.is_set():
                    break
                if not failing:  # once per streak, not 200 times a second
                    log.warning("node %d: SYNC send failed: %s", self.node_id, exc)
                failing = True
            next_t += period
            now = time.monotonic()
            if now - next_t > period:  # fell behind (machine busy): skip, don't burst
                next_t = now + period
            if self._master_heartbeat_on and now >= next_hb:
                self._send_master_heartbeat()
                next_hb = now + hb_period
            self._watchdog()

    def _sync_time_for(self, t_rx: float) -> float:
        """Host time of the SYNC a TPDO received at ``t_rx`` answers: the oldest unanswered SYNC
        (first-in first-out: CAN keeps frame order and does not drop frames, so this holds
        however late the TPDO is). SYNCs the drive cannot answer are forgotten when its heartbeat
        says it is not Operational, and the queue keeps at most 0.5 s of SYNCs. Should an answer
        be lost anyway, every later TPDO would pair with the SYNC before its own, and a newer
        SYNC would always still be outstanding when a TPDO arrives; when that has been so for
        every TPDO during :attr:`pairing_window_s`, the oldest outstanding SYNC is dropped."""
        with self._sync_lock:
            if not self._sync_times:
                return t_rx
            t_sync = self._sync_times.popleft()
            self._pair_min_backlog = min(self._pair_min_backlog, len(self._sync_times))
            if self._pair_window_start == -math.inf:
                self._pair_window_start = t_rx
            elif t_rx - self._pair_window_start >= self.pairing_window_s:
                if self._pair_min_backlog >= 1 and self._sync_times:
                    self._sync_times.popleft()
                    self.resyncs += 1
                    log.info("node %d: TPDO/SYNC pairing re-synchronised (an answer was lost)", self.node_id)
                self._pair_window_start = t_rx
                self._pair_min_backlog = len(self._sync_times)
            return t_sync

    def _sample_tpdo(self, k: int, data: bytearray) -> dict[int, int] | None:
        """Sample TPDO ``k + 1``'s values by object index; None before the layout is settled or
        for a frame the layout does not decode."""
        if not self._layout_known:
            return None
        try:
            return cia402.unpack_pdo(self.sample_tpdos[k], bytes(data))
        except cia402.CodecError as exc:
            log.debug("node %d: TPDO%d ignored: %s", self.node_id, k + 1, exc)
            return None

    def _on_tpdo1(self, can_id: int, data: bytearray, timestamp: float) -> None:
        values = self._sample_tpdo(0, data)
        if values is None:
            return
        now = self.clock()
        t = self._sync_time_for(now)
        self._last_tpdo_rx = now
        self.tpdo_count += 1
        pending, self._pending_tpdo1 = self._pending_tpdo1, (t, now, values)
        if pending is not None:  # its TPDO2 never came
            self._emit(pending, {})

    def _on_tpdo2(self, can_id: int, data: bytearray, timestamp: float) -> None:
        values = self._sample_tpdo(1, data)
        if values is None:
            return
        pending, self._pending_tpdo1 = self._pending_tpdo1, None
        if pending is not None:
            self._emit(pending, values)

    def _emit(self, tpdo1: tuple[float, float, dict[int, int]], tpdo2: dict[int, int]) -> None:
        """One sample from a SYNC's two TPDOs (``tpdo2`` empty: it never came)."""
        t, t_rx, values = tpdo1
        values = {**values, **tpdo2}
        c = self.config
        velocity = values.get(cia402.VELOCITY_ACTUAL)
        statusword = values.get(cia402.STATUSWORD)
        stamp = values.get(cia402.HIGH_RES_TIMESTAMP)
        last = self._last_sw
        self._push_sample(
            MotorSample(
                t,
                c.counts_to_rad(values[cia402.POSITION_ACTUAL]),
                math.nan if velocity is None else c.counts_to_rad(velocity),
                statusword if statusword is not None else (last[1] if last is not None else 0),
                stamp,
                None if stamp is None else t_rx,
            )
        )
        if statusword is None:  # it was in the TPDO that never came: nothing new for waiters
            return
        with self._sw_cond:  # waiters see a statusword only once its sample is in the buffer
            self._last_sw = (t, statusword)
            self._sw_cond.notify_all()

    def _on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if not data:
            return
        self._last_heartbeat = self.clock()
        self._heartbeat_state = data[0]
        if data[0] != 0x05:  # not Operational: it answers no SYNC, none is outstanding
            with self._sync_lock:
                self._sync_times.clear()

    def _on_emcy(self, can_id: int, data: bytearray, timestamp: float) -> None:
        try:
            emcy = cia402.Emcy.decode(bytes(data))
        except ValueError:
            log.warning("node %d: malformed EMCY %s", self.node_id, bytes(data).hex())
            return
        t = self.clock()
        self.emcy_history.append((t, emcy))
        log.info("node %d: %s", self.node_id, emcy)
        for cb in list(self._emcy_callbacks):
            cb(t, emcy)

    def add_emcy_callback(self, callback: Callable[[float, cia402.Emcy], None]) -> None:
        """``callback(t_host_s, emcy)`` for every EMCY frame (reset frames have ``emcy.code == 0``)."""
        self._emcy_callbacks.append(callback)

    def _watchdog(self) -> None:
        notifier = self.network.notifier
        error = notifier.exception if notifier is not None else None
        if error is not None and self._host_fault is None:  # the receive thread died (bus gone)
            self._host_fault = FaultInfo(
                0x8100,  # communication
                f"CAN receive stopped: {error}",
                0x11,
                self.clock(),
                source="bus",
            )
            log.error("node %d: %s", self.node_id, self._host_fault.reason)
            with self._sw_cond:
                self._sw_cond.notify_all()
            return
        hb = self._heartbeat_ms
        if not hb or self._last_heartbeat is None or self._host_fault is not None:
            return
        silent_s = self.clock() - self._last_heartbeat
        if silent_s > self.options.heartbeat_lost * hb / 1000.0:
            self._host_fault = FaultInfo(
                cia402.ERR_HEARTBEAT,
                f"heartbeat lost: node {self.node_id} silent for {silent_s * 1000:.0f} ms (heartbeat every {hb} ms)",
                0x11,
                self.clock(),
                source="heartbeat",
            )
            log.error("node %d: %s", self.node_id, self._host_fault.reason)
            with self._sw_cond:
                self._sw_cond.notify_all()
            # best effort: ask the drive to stop; it may still be listening
            threading.Thread(target=self._emergency_quick_stop, daemon=True).start()

    def _emergency_quick_stop(self) -> None:
        try:
            self._cw(cia402.CMD_QUICK_STOP)
        except DriverError as exc:
            log.error("node %d: quick stop after heartbeat loss failed: %s", self.node_id, exc)

    def _clear_host_fault(self) -> None:
        fault = self._host_fault
        if fault is None:
            return
        if fault.source == "bus":
            raise ConnectionLost(fault.code, fault.reason, None, "reopen the motor")
        hb = self._heartbeat_ms
        if self._last_heartbeat is not None and self._last_heartbeat > fault.t_host_s:
            self._host_fault = None
            return
        deadline = self.clock() + 3.0 * hb / 1000.0
        while self.clock() < deadline:  # give a returning drive a few periods to be heard
            time.sleep(hb / 4000.0)
            if self._last_heartbeat is not None and self._last_heartbeat > fault.t_host_s:
                self._host_fault = None
                return
        raise HeartbeatLost(fault.code, fault.reason, None, "fault reset refused: still no heartbeat")

    def _statusword_after(self, t: float, timeout: float) -> int:
        deadline = self.clock() + timeout
        with self._sw_cond:
            while True:
                if self._host_fault is not None:
                    raise self._host_fault.to_exception()
                last = self._last_sw
                if last is not None and last[0] > t:
                    return last[1]
                remaining = deadline - self.clock()
                if remaining <= 0 or not self._tpdos_expected():
                    break
                self._sw_cond.wait(min(remaining, 0.05))
        # no TPDOs (no SYNC, node not Operational) or none in time: ask directly
        return self._read_object(cia402.STATUSWORD)

    def _tpdos_expected(self) -> bool:
        """Worth waiting for a TPDO: we produce SYNC and the drive has answered before, or
        another master's SYNCs brought TPDOs within the last 0.25 s."""
        if self._last_tpdo_rx is None:
            return False
        return bool(self.options.sync_hz) or self.clock() - self._last_tpdo_rx < 0.25

    @property
    def heartbeat_state(self) -> int | None:
        """NMT state byte of the last heartbeat (0x05 Operational, 0x7F Pre-operational, ...)."""
        return self._heartbeat_state

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._master_heartbeat_on and self._host_fault is None:
            try:  # a deliberate close: the drive stops watching our heartbeat, and keeps its state
                self._write_object(cia402.CONSUMER_HEARTBEAT_TIME, 1, 0)
            except DriverError as exc:
                log.warning("node %d: could not switch off the heartbeat consumer: %s", self.node_id, exc)
        self._stop.set()
        if self._sync_thread is not None and self._sync_thread is not threading.current_thread():
            self._sync_thread.join(timeout=2.0)
        try:
            self.network.disconnect()
        except Exception as exc:  # the receive thread may have died with the bus
            log.warning("node %d: disconnect: %s", self.node_id, exc)
        if self.on_close is not None:
            self.on_close()


def canopen_object_dictionary() -> canopen.ObjectDictionary:
    """A ``canopen`` object dictionary of every object in :data:`cia402.OBJECTS`, for masters
    built on the ``canopen`` library (e.g. ``canopen.profiles.p402.BaseNode402``)."""
    from canopen.objectdictionary import ODRecord, ODVariable

    od = canopen.ObjectDictionary()
    by_index: dict[int, list[cia402.ObjectSpec]] = {}
    for spec in cia402.OBJECTS.values():
        by_index.setdefault(spec.index, []).append(spec)

    def variable(spec: cia402.ObjectSpec) -> ODVariable:
        var = ODVariable(spec.name, spec.index, spec.subindex)
        var.data_type = spec.dtype.code
        var.access_type = spec.access.value
        var.default = spec.default  # type: ignore[assignment]  # canopen annotates int but stores strings too
        return var

    for index, specs in sorted(by_index.items()):
        if len(specs) == 1 and specs[0].subindex == 0:
            od.add_object(variable(specs[0]))
            continue
        record = ODRecord(specs[0].name.split(":")[0], index)
        for spec in sorted(specs, key=lambda s: s.subindex):
            record.add_member(variable(spec))
        od.add_object(record)
    return od
