"""CANopen slave front end of the simulated drive, on any python-can bus.

:class:`SimCanNode` puts a :class:`~sim.drive.model.SimDrive` on a bus as CANopen node N:

* NMT slave (boot-up, start / stop / pre-operational / reset node / reset communication),
* SDO server: expedited and segmented upload and download, aborts with the drive's codes
  (block transfer is answered with abort 0x05040001),
* PDOs from the drive's own 0x1400-0x1A03 objects: synchronous TPDOs (type 1-240) sampled when
  SYNC arrives and sent right after it (one snapshot, including the drive's time stamp 0x1013,
  the drive clock in µs at that latch), event-driven TPDOs (254/255) on change or event timer,
  RPDOs applied on reception (254/255) or at the next SYNC (0-240),
* heartbeat producer (0x1017; stops while the drive's ``heartbeat_loss`` fault is injected),
* heartbeat consumer (0x1016:1 = master node << 16 | time in ms): the master's silence is fault
  0x8130, so a crashed host stops the motor,
* EMCY producer (0x80 + N) fed by the drive's fault events.

The node owns two threads: a receiver (``bus.recv``) and a ticker (motion, heartbeat,
event-driven TPDOs). Every frame goes out through one send lock.

The motor URL scheme ``sim://`` (a simulated drive on a private python-can ``virtual`` channel
with the CANopen driver connected to it) is served by :mod:`service.simdevices`.
"""

from __future__ import annotations

import collections
import logging
import queue
import random
import struct
import threading
import time
from dataclasses import dataclass, field

import can

from drivers.servo import cia402
from sim.drive.model import ObjectAccessError, SimDrive

log = logging.getLogger(__name__)

NMT_BOOT = 0x00
NMT_STOPPED = 0x04
NMT_OPERATIONAL = 0x05
NMT_PRE_OPERATIONAL = 0x7F

_NMT_START, _NMT_STOP, _NMT_PRE_OP, _NMT_RESET_NODE, _NMT_RESET_COMM = 0x01, 0x02, 0x80, 0x81, 0x82


@dataclass
class _SdoTransfer:
    kind: str  # "upload" | "download"
    index: int
    subindex: int
    toggle: int = 0
    data: bytearray = field(default_factory=bytearray)
    size: int | None = None


class SimCanNode:
    """A simulated CiA 402 drive as CANopen node ``drive.node_id`` on ``bus`` (see module docstring)."""

    tick_s = 0.002

    def __init__(self, bus: can.BusABC, drive: SimDrive | None = None, *, node_id: int = 1) -> None:
        self.drive = drive if drive is not None else SimDrive(node_id)
        self.node_id = self.drive.node_id
        self.bus = bus
        self.nmt_state = NMT_BOOT
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._sdo: _SdoTransfer | None = None
        self._sync_count = 0
        self._tpdo_sync_counter = [0, 0, 0, 0]
        self._tpdo_last: list[bytes | None] = [None, None, None, None]
        self._tpdo_last_t = [0.0, 0.0, 0.0, 0.0]
        self._rpdo_pending: dict[int, bytes] = {}
        self._next_heartbeat = 0.0
        self._emcy_queue: list[tuple[int, int]] = []
        self._emcy_lock = threading.Lock()
        self.drive.add_emcy_listener(self._on_drive_emcy)
        self.frames_in = 0
        self.frames_out = 0
        self.nmt_commands: list[int] = []  # every NMT command addressed to this node, in order
        #: (drive clock, position actual) at every SYNC received, newest last
        self.sync_log: collections.deque[tuple[float, int]] = collections.deque(maxlen=2000)
        #: extra delay before the synchronous TPDOs of a SYNC leave (a slow drive or a busy bus)
        self.tpdo_latency_s = 0.0
        #: the synchronous TPDOs of this many coming SYNCs are not sent (frames lost)
        self.drop_tpdos = 0
        #: a drive slow to process SYNC: it latches this long after the SYNC reached it, plus a
        #: uniformly random extra of up to ``sync_delay_jitter_s`` (seeded: reproducible)
        self.sync_delay_s = 0.0
        self.sync_delay_jitter_s = 0.0
        self._sync_delay_rng = random.Random(node_id)
        self._master_heartbeat_seen: float | None = None
        self._delayed: queue.SimpleQueue[tuple[float, list[tuple[int, bytes]]]] = queue.SimpleQueue()

    # ------------------------------------------------------------------------------------------
    def start(self) -> SimCanNode:
        self._boot()
        for target, name in ((self._rx_loop, "rx"), (self._tick_loop, "tick"), (self._delayed_loop, "late")):
            t = threading.Thread(target=target, name=f"sim-can-node{self.node_id}-{name}", daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(timeout=2.0)
        self._threads.clear()

    def __enter__(self) -> SimCanNode:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------------------------------------
    def _send(self, can_id: int, data: bytes) -> None:
        msg = can.Message(arbitration_id=can_id, data=data, is_extended_id=False)
        with self._send_lock:
            try:
                self.bus.send(msg)
                self.frames_out += 1
            except (can.CanError, OSError) as exc:
                if not self._stop.is_set():
                    log.warning("node %d: send 0x%03X failed: %s", self.node_id, can_id, exc)

    def _boot(self) -> None:
        self.nmt_state = NMT_BOOT
        self._send(0x700 + self.node_id, bytes([NMT_BOOT]))
        self.nmt_state = NMT_PRE_OPERATIONAL
        self._next_heartbeat = time.monotonic()

    def _on_drive_emcy(self, code: int, register: int) -> None:
        # called under the drive lock: queue it, the ticker sends it
        with self._emcy_lock:
            self._emcy_queue.append((code, register))

    def _flush_emcy(self) -> None:
        with self._emcy_lock:
            pending, self._emcy_queue = self._emcy_queue, []
        cob = int(self.drive.raw(cia402.COB_ID_EMCY))
        for code, register in pending:
            if self.nmt_state != NMT_STOPPED and not cob & (1 << 31):
                self._send(cob & 0x7FF, cia402.Emcy(code, register).encode())

    # ------------------------------------------------------------------------------------------
    def _rx_loop(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self.bus.recv(timeout=0.05)
            except (can.CanError, OSError, ValueError) as exc:
                if not self._stop.is_set():
                    log.error("node %d: bus receive failed: %s", self.node_id, exc)
                return
            if msg is None or msg.is_error_frame or msg.is_extended_id or msg.is_remote_frame:
                continue
            self.frames_in += 1
            try:
                self._dispatch(msg.arbitration_id, bytes(msg.data))
            except Exception:  # one bad frame must not kill the node
                log.exception("node %d: error handling frame 0x%03X", self.node_id, msg.arbitration_id)

    def _dispatch(self, can_id: int, data: bytes) -> None:
        n = self.node_id
        if can_id == 0x000:
            if len(data) == 2 and data[1] in (0, n):
                self._nmt(data[0])
            return
        if 0x701 <= can_id <= 0x77F and can_id - 0x700 == self._consumed_node():
            self._master_heartbeat_seen = time.monotonic()
            return
        if self.nmt_state == NMT_STOPPED:
            return
        sync_cob = int(self.drive.raw(cia402.COB_ID_SYNC)) & 0x7FF
        if can_id == sync_cob:
            self._on_sync()
            return
        if can_id == 0x600 + n:
            self._sdo_request(data)
            return
        if self.nmt_state == NMT_OPERATIONAL:
            for k in range(4):
                cob = int(self.drive.raw(cia402.RPDO_COMM + k, 1))
                if not cob & (1 << 31) and cob & 0x7FF == can_id:
                    ttype = int(self.drive.raw(cia402.RPDO_COMM + k, 2))
                    if ttype >= 254:
                        self._apply_rpdo(k, data)
                    else:
                        self._rpdo_pending[k] = data
                    return

    def _nmt(self, command: int) -> None:
        self.nmt_commands.append(command)
        if command == _NMT_START:
            self.nmt_state = NMT_OPERATIONAL
        elif command == _NMT_STOP:
            self.nmt_state = NMT_STOPPED
        elif command == _NMT_PRE_OP:
            self.nmt_state = NMT_PRE_OPERATIONAL
        elif command in (_NMT_RESET_NODE, _NMT_RESET_COMM):
            self._sdo = None
            self._rpdo_pending.clear()
            self._tpdo_last = [None, None, None, None]
            self._boot()

    # ------------------------------------------------------------------------------------------
    # PDOs
    # ------------------------------------------------------------------------------------------
    def _apply_rpdo(self, k: int, data: bytes) -> None:
        entries = self.drive.pdo_mapping(cia402.RPDO_MAP + k)
        need = sum(bits for _, _, bits in entries) // 8
        if len(data) < need:
            self.drive_emcy(0x8210)  # PDO not processed due to length error
            return
        offset = 0
        with self.drive.lock:
            for index, sub, bits in entries:
                spec = cia402.object_spec(index, sub)
                size = bits // 8
                try:
                    self.drive.write(index, sub, spec.dtype.decode(data[offset : offset + size]))
                except ObjectAccessError as exc:
                    log.info("node %d: RPDO%d write refused: %s", self.node_id, k + 1, exc)
                offset += size

    def drive_emcy(self, code: int) -> None:
        """Send an EMCY that is not a drive fault (communication errors)."""
        self._send(0x80 + self.node_id, cia402.Emcy(code, cia402.error_register_for(code)).encode())

    def _pack_tpdo(self, k: int) -> bytes:
        out = bytearray()
        for index, sub, bits in self.drive.pdo_mapping(cia402.TPDO_MAP + k):
            spec = cia402.object_spec(index, sub)
            value = self.drive.read(index, sub)
            out += spec.dtype.encode(value)[: bits // 8]
        return bytes(out)

    def _on_sync(self) -> None:
        delay = self.sync_delay_s + self.sync_delay_jitter_s * self._sync_delay_rng.random()
        if delay > 0:
            time.sleep(delay)
        for k, data in sorted(self._rpdo_pending.items()):
            self._apply_rpdo(k, data)
        self._rpdo_pending.clear()
        frames: list[tuple[int, bytes]] = []
        with self.drive.latched():  # one snapshot for every synchronous TPDO of this SYNC
            self.sync_log.append((self.drive.clock(), self.drive.read(cia402.POSITION_ACTUAL)))
            if self.nmt_state != NMT_OPERATIONAL:
                return
            for k in range(4):
                cob = int(self.drive.raw(cia402.TPDO_COMM + k, 1))
                ttype = int(self.drive.raw(cia402.TPDO_COMM + k, 2))
                if cob & (1 << 31) or ttype > 240:
                    continue
                self._tpdo_sync_counter[k] += 1
                every = max(1, ttype)
                if self._tpdo_sync_counter[k] >= every:
                    self._tpdo_sync_counter[k] = 0
                    frames.append((cob & 0x7FF, self._pack_tpdo(k)))
        if self.drop_tpdos > 0:  # simulated loss of this SYNC's answer
            self.drop_tpdos -= 1
            return
        if self.tpdo_latency_s > 0:  # held back in order, like frames queued behind others on a bus
            self._delayed.put((time.monotonic() + self.tpdo_latency_s, frames))
        else:
            self._send_all(frames)

    def _delayed_loop(self) -> None:
        while not self._stop.is_set():
            try:
                due, frames = self._delayed.get(timeout=0.1)
            except queue.Empty:
                continue
            wait = due - time.monotonic()
            if wait > 0 and self._stop.wait(wait):
                return
            self._send_all(frames)

    def _send_all(self, frames: list[tuple[int, bytes]]) -> None:
        for cob, data in frames:
            self._send(cob, data)

    def _event_tpdos(self, now: float) -> None:
        if self.nmt_state != NMT_OPERATIONAL:
            return
        for k in range(4):
            cob = int(self.drive.raw(cia402.TPDO_COMM + k, 1))
            ttype = int(self.drive.raw(cia402.TPDO_COMM + k, 2))
            if cob & (1 << 31) or ttype < 254:
                continue
            inhibit = int(self.drive.raw(cia402.TPDO_COMM + k, 3)) * 1e-4
            timer = int(self.drive.raw(cia402.TPDO_COMM + k, 5)) * 1e-3
            if now - self._tpdo_last_t[k] < inhibit:
                continue
            data = self._pack_tpdo(k)
            if data != self._tpdo_last[k] or (timer > 0 and now - self._tpdo_last_t[k] >= timer):
                self._tpdo_last[k] = data
                self._tpdo_last_t[k] = now
                self._send(cob & 0x7FF, data)

    # ------------------------------------------------------------------------------------------
    def _tick_loop(self) -> None:
        while not self._stop.wait(self.tick_s):
            now = time.monotonic()
            try:
                self.drive.advance()
                self._flush_emcy()
                self._event_tpdos(now)
                self._check_master_heartbeat(now)
                period_ms = int(self.drive.raw(cia402.PRODUCER_HEARTBEAT_TIME))
                if period_ms > 0 and now >= self._next_heartbeat:
                    self._next_heartbeat = now + period_ms / 1000.0
                    if not self.drive.silent:
                        self._send(0x700 + self.node_id, bytes([self.nmt_state]))
            except Exception:
                log.exception("node %d: tick failed", self.node_id)

    def _consumed_node(self) -> int:
        return (int(self.drive.raw(cia402.CONSUMER_HEARTBEAT_TIME, 1)) >> 16) & 0x7F

    def _check_master_heartbeat(self, now: float) -> None:
        """Heartbeat consumer (0x1016:1 = node << 16 | ms): monitoring starts with the first
        heartbeat heard; silence longer than the time is fault 0x8130 (the motor is stopped)."""
        entry = int(self.drive.raw(cia402.CONSUMER_HEARTBEAT_TIME, 1))
        timeout_ms = entry & 0xFFFF
        seen = self._master_heartbeat_seen
        if not timeout_ms or not (entry >> 16) & 0x7F or seen is None:
            return
        if now - seen > timeout_ms / 1000.0:
            self._master_heartbeat_seen = None  # report once; watch again from the next one
            log.warning("node %d: heartbeat of node %d lost", self.node_id, (entry >> 16) & 0x7F)
            self.drive.communication_fault(cia402.ERR_HEARTBEAT)

    # ------------------------------------------------------------------------------------------
    # SDO server
    # ------------------------------------------------------------------------------------------
    def _sdo_reply(self, data: bytes) -> None:
        self._send(0x580 + self.node_id, data.ljust(8, b"\x00"))

    def _sdo_abort(self, index: int, subindex: int, code: int) -> None:
        self._sdo = None
        self._sdo_reply(struct.pack("<BHBI", 0x80, index, subindex, code))

    def _sdo_request(self, data: bytes) -> None:
        if len(data) != 8:
            return  # SDO frames are always 8 bytes; a short one is ignored like on a real node
        ccs = data[0] >> 5
        index, subindex = struct.unpack_from("<HB", data, 1)
        try:
            if ccs == 1:
                self._sdo_initiate_download(data, index, subindex)
            elif ccs == 0:
                self._sdo_download_segment(data)
            elif ccs == 2:
                self._sdo_initiate_upload(index, subindex)
            elif ccs == 3:
                self._sdo_upload_segment(data)
            elif ccs == 4:
                self._sdo = None  # client abort
            else:  # block transfers and anything else
                self._sdo_abort(index, subindex, cia402.ABORT_COMMAND)
        except ObjectAccessError as exc:
            self._sdo_abort(exc.index, exc.subindex, exc.abort_code)

    def _check_pdo_config_write(self, index: int, subindex: int) -> None:
        """PDO mapping may change only while the PDO is invalid (COB-ID bit 31 set)."""
        for comm, mapping in ((cia402.RPDO_COMM, cia402.RPDO_MAP), (cia402.TPDO_COMM, cia402.TPDO_MAP)):
            if mapping <= index < mapping + 4:
                cob = int(self.drive.raw(comm + index - mapping, 1))
                if not cob & (1 << 31):
                    raise ObjectAccessError(index, subindex, cia402.ABORT_DEVICE_STATE)

    def _write(self, index: int, subindex: int, payload: bytes, *, size_indicated: bool = True) -> None:
        self._check_pdo_config_write(index, subindex)
        spec = self.drive.spec(index, subindex)
        if not size_indicated and spec.dtype.is_integer and len(payload) > spec.dtype.size:
            payload = payload[: spec.dtype.size]  # expedited without size: 4 bytes, padded
        self.drive.write_bytes(index, subindex, payload)
        if (index, subindex) == (cia402.PRODUCER_HEARTBEAT_TIME, 0):
            self._next_heartbeat = time.monotonic()
        if (index, subindex) == (cia402.CONSUMER_HEARTBEAT_TIME, 1):
            self._master_heartbeat_seen = None  # monitoring restarts with the next heartbeat

    def _sdo_initiate_download(self, data: bytes, index: int, subindex: int) -> None:
        self._sdo = None
        expedited, size_indicated = bool(data[0] & 0x02), bool(data[0] & 0x01)
        if expedited:
            n = (data[0] >> 2) & 0x03 if size_indicated else 0
            self._write(index, subindex, data[4 : 8 - n], size_indicated=size_indicated)
            self._sdo_reply(struct.pack("<BHB", 0x60, index, subindex))
            return
        self.drive.spec(index, subindex)  # no object: abort now, not after the segments
        self._check_pdo_config_write(index, subindex)
        size = struct.unpack_from("<I", data, 4)[0] if size_indicated else None
        self._sdo = _SdoTransfer("download", index, subindex, size=size)
        self._sdo_reply(struct.pack("<BHB", 0x60, index, subindex))

    def _sdo_download_segment(self, data: bytes) -> None:
        tr = self._sdo
        if tr is None or tr.kind != "download":
            self._sdo_abort(0, 0, cia402.ABORT_COMMAND)
            return
        toggle = (data[0] >> 4) & 1
        if toggle != tr.toggle:
            self._sdo_abort(tr.index, tr.subindex, cia402.ABORT_TOGGLE)
            return
        unused = (data[0] >> 1) & 0x07
        tr.data += data[1 : 8 - unused]
        last = bool(data[0] & 0x01)
        if last:
            self._sdo = None
            if tr.size is not None and tr.size != len(tr.data):
                code = cia402.ABORT_LENGTH_TOO_HIGH if len(tr.data) > tr.size else cia402.ABORT_LENGTH_TOO_LOW
                self._sdo_abort(tr.index, tr.subindex, code)
                return
            try:
                self._write(tr.index, tr.subindex, bytes(tr.data))
            except ObjectAccessError as exc:
                self._sdo_abort(exc.index, exc.subindex, exc.abort_code)
                return
        else:
            tr.toggle ^= 1
        self._sdo_reply(bytes([0x20 | (toggle << 4)]))

    def _sdo_initiate_upload(self, index: int, subindex: int) -> None:
        self._sdo = None
        payload = self.drive.read_bytes(index, subindex)
        if len(payload) <= 4 and len(payload) > 0:
            n = 4 - len(payload)
            self._sdo_reply(struct.pack("<BHB", 0x43 | (n << 2), index, subindex) + payload)
            return
        self._sdo = _SdoTransfer("upload", index, subindex, data=bytearray(payload))
        self._sdo_reply(struct.pack("<BHBI", 0x41, index, subindex, len(payload)))

    def _sdo_upload_segment(self, data: bytes) -> None:
        tr = self._sdo
        if tr is None or tr.kind != "upload":
            self._sdo_abort(0, 0, cia402.ABORT_COMMAND)
            return
        toggle = (data[0] >> 4) & 1
        if toggle != tr.toggle:
            self._sdo_abort(tr.index, tr.subindex, cia402.ABORT_TOGGLE)
            return
        chunk, tr.data = tr.data[:7], tr.data[7:]
        last = not tr.data
        self._sdo_reply(bytes([(toggle << 4) | ((7 - len(chunk)) << 1) | int(last)]) + bytes(chunk))
        if last:
            self._sdo = None
        else:
            tr.toggle ^= 1
