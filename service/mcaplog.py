"""The raw-data log of a measurement: one MCAP file, written on its own thread.

Channels (Foxglove shows the ``foxglove.*`` ones natively):

=========================  ==============================  ===========================================
topic                      schema / encoding               content
=========================  ==============================  ===========================================
``/lms100/telegram``       (none) / ``sick-cola-a|b``      every LMDscandata telegram exactly as read
``/lms100/scan``           ``foxglove.LaserScan``          the decoded scan in frame ``scan_plane``
``/motor/joint``           ``foxglove.JointStates``        timestamped shaft angle and velocity
``/tf``                    ``foxglove.FrameTransform``     ``world -> rig`` and ``rig -> scan_plane``
``/cloud``                 ``foxglove.PointCloud``         the mapped cloud (float32 x y z, world)
``/lrms/measurement``      ``lrms.Measurement`` / json     request, configuration, calibration
``/lrms/event``            ``lrms.Event`` / json           gaps, reconnects, faults, cancellation
``/lrms/result``           ``lrms.Result`` / json          the fit result (or the failure)
=========================  ==============================  ===========================================

Every message's log time is the host time (ns since the epoch) at which the data was read; that
is what :mod:`service.cli.replay` feeds back through the same pipeline. A time inside a JSON
message is Foxglove's ``{"sec", "nsec"}`` object (:func:`foxglove_time`), never an integer of
nanoseconds: those exceed 2^53, which a JavaScript reader (Foxglove) rounds.

The writer closes a chunk about once a second (``Writer.flush``) and flushes the file, so a
process killed mid-sweep leaves every completed chunk readable: :func:`iter_log` reads a file
with or without its summary, and stops cleanly where a truncated file ends;
:func:`service.mcaprecovery.recover_log` rewrites such a file into a complete, indexed one (the
service does so on restart).
"""

from __future__ import annotations

import contextlib
import json
import math
import queue
import struct
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.JointStates_pb2 import JointStates
from foxglove_schemas_protobuf.LaserScan_pb2 import LaserScan
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from mcap.exceptions import InvalidMagic, McapError
from mcap.reader import NonSeekingReader
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import build_file_descriptor_set
from numpy.typing import ArrayLike, NDArray

from service.errors import ServiceError

TOPIC_TELEGRAM = "/lms100/telegram"
TOPIC_SCAN = "/lms100/scan"
TOPIC_MOTOR = "/motor/joint"
TOPIC_TF = "/tf"
TOPIC_CLOUD = "/cloud"
TOPIC_MEASUREMENT = "/lrms/measurement"
TOPIC_EVENT = "/lrms/event"
TOPIC_RESULT = "/lrms/result"

_PROTO: dict[str, Any] = {
    TOPIC_SCAN: LaserScan,
    TOPIC_MOTOR: JointStates,
    TOPIC_TF: FrameTransform,
    TOPIC_CLOUD: PointCloud,
}
_JSON_SCHEMA: dict[str, str] = {
    TOPIC_MEASUREMENT: "lrms.Measurement",
    TOPIC_EVENT: "lrms.Event",
    TOPIC_RESULT: "lrms.Result",
}
_PROTO_BY_NAME = {cls.DESCRIPTOR.full_name: cls for cls in _PROTO.values()}

#: Foxglove's time in JSON: whole seconds and nanoseconds, both integers a JavaScript number holds exactly.
TIME_SCHEMA: dict[str, Any] = {
    "type": "object",
    "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999},
    },
    "required": ["sec", "nsec"],
}
_JSON_PROPERTIES: dict[str, dict[str, Any]] = {
    TOPIC_EVENT: {"kind": {"type": "string"}, "time": TIME_SCHEMA},
}


def foxglove_time(t_ns: int) -> dict[str, int]:
    """``{"sec", "nsec"}`` of a host time in integer ns since the epoch (Foxglove's JSON time)."""
    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    return {"sec": sec, "nsec": nsec}


def time_ns_of(value: Any) -> int:
    """Integer ns of a logged time: a ``{"sec", "nsec"}`` object, or the plain integer older logs carry."""
    if isinstance(value, dict):
        return int(value["sec"]) * 1_000_000_000 + int(value["nsec"])
    if isinstance(value, int | str) and not isinstance(value, bool):
        return int(value)
    raise McapLogError(f"not a logged time: {value!r}")


def json_safe(obj: Any) -> Any:
    """``obj`` with numpy scalars made plain and non-finite floats replaced by None (strict JSON)."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


MCAP_MAGIC = b"\x89MCAP0\r\n"


class McapLogError(ServiceError):
    """The raw log could not be written or read."""


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        if not n:
            out.append(b)
            return bytes(out)
        out.append(b | 0x80)


_RANGES_TAG = bytes([(LaserScan.DESCRIPTOR.fields_by_name["ranges"].number << 3) | 2])
_INTENSITIES_TAG = bytes([(LaserScan.DESCRIPTOR.fields_by_name["intensities"].number << 3) | 2])


def _packed_doubles(tag: bytes, values: NDArray[np.float64]) -> bytes:
    """A packed ``repeated double`` field: tag, byte length, little-endian doubles (protobuf's wire format)."""
    if values.size == 0:
        return b""
    payload = values.astype("<f8", copy=False).tobytes()
    return tag + _varint(len(payload)) + payload


def _stamp(msg_ts: Any, t_ns: int) -> None:
    msg_ts.seconds = t_ns // 1_000_000_000
    msg_ts.nanos = t_ns % 1_000_000_000


def plane_rotation(beta: float) -> NDArray[np.float64]:
    """Rotation (rig <- scan_plane) of the scan-plane frame at motor angle ``beta``.

    The scan-plane frame has x along the shaft (+y of the rig, alpha = 0) and y along the
    in-plane direction alpha = +90 deg, ``(cos beta, 0, sin beta)``, so a LaserScan angle in
    that frame is exactly the seed's alpha.
    """
    cb, sb = np.cos(beta), np.sin(beta)
    return np.array([[0.0, cb, sb], [1.0, 0.0, 0.0], [0.0, sb, -cb]])


def quaternion(rot: NDArray[np.float64]) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix (Shepperd's method, branch on the largest diagonal term).

    Per-scan transforms go through this instead of ``scipy.spatial.transform.Rotation`` (which
    costs ~20x more per call); the tests check both agree up to the quaternion's sign.
    """
    m = [[float(v) for v in row] for row in np.asarray(rot, dtype=np.float64)]
    tr = m[0][0] + m[1][1] + m[2][2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        return ((m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s, 0.25 * s)
    if m[0][0] > m[1][1] and m[0][0] > m[2][2]:
        s = 2.0 * math.sqrt(1.0 + m[0][0] - m[1][1] - m[2][2])
        return (0.25 * s, (m[0][1] + m[1][0]) / s, (m[0][2] + m[2][0]) / s, (m[2][1] - m[1][2]) / s)
    if m[1][1] > m[2][2]:
        s = 2.0 * math.sqrt(1.0 + m[1][1] - m[0][0] - m[2][2])
        return ((m[0][1] + m[1][0]) / s, 0.25 * s, (m[1][2] + m[2][1]) / s, (m[0][2] - m[2][0]) / s)
    s = 2.0 * math.sqrt(1.0 + m[2][2] - m[0][0] - m[1][1])
    return ((m[0][2] + m[2][0]) / s, (m[1][2] + m[2][1]) / s, 0.25 * s, (m[1][0] - m[0][1]) / s)


def _transform(t_ns: int, parent: str, child: str, rot: NDArray[np.float64], trans: ArrayLike) -> bytes:
    msg = FrameTransform()
    _stamp(msg.timestamp, t_ns)
    msg.parent_frame_id = parent
    msg.child_frame_id = child
    tx, ty, tz = (float(v) for v in np.asarray(trans, dtype=np.float64))
    msg.translation.x, msg.translation.y, msg.translation.z = tx, ty, tz
    msg.rotation.x, msg.rotation.y, msg.rotation.z, msg.rotation.w = quaternion(rot)
    return bytes(msg.SerializeToString())


@dataclass
class _Item:
    topic: str
    t_ns: int
    build: Callable[[], bytes]
    encoding: str = ""


_STOP = object()


class McapLog:
    """MCAP writer on its own thread. All ``log_*`` methods are cheap and thread-safe."""

    def __init__(
        self,
        path: str | Path,
        flush_interval_s: float = 1.0,
        compression: str = "zstd",
        chunk_size: int = 1 << 20,
    ) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
        if compression not in comp:
            raise McapLogError(f"unknown MCAP compression {compression!r} (zstd, lz4 or none)")
        try:
            self._fh: BinaryIO = open(self.path, "wb")  # noqa: SIM115 (closed by the writer thread)
        except OSError as exc:
            raise McapLogError(f"cannot create raw log {self.path}: {exc.strerror or exc}") from None
        self._writer = Writer(self._fh, chunk_size=chunk_size, compression=comp[compression])
        self._writer.start(profile="", library="lrms")
        self._channels: dict[tuple[str, str], int] = {}
        self._flush_interval = flush_interval_s
        self._q: queue.SimpleQueue[_Item | object] = queue.SimpleQueue()
        self._error: BaseException | None = None
        self._closed = False
        self.messages_written = 0
        self.flushes = 0
        self.messages_flushed = 0  # messages in closed chunks, on disk (page cache) after a crash
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name=f"mcap:{self.path.name}", daemon=True)
        self._thread.start()

    # -- producer side --------------------------------------------------------------------
    def _put(self, item: _Item) -> None:
        if self._closed:
            raise McapLogError(f"raw log {self.path} is closed")
        if self._error is not None:
            raise McapLogError(f"raw log {self.path} failed: {self._error}")
        self._q.put(item)

    @property
    def backlog(self) -> int:
        return self._q.qsize()

    def log_telegram(self, t_ns: int, payload: bytes, dialect: str) -> None:
        """A telegram exactly as read (frame included); ``dialect`` is ``"a"`` or ``"b"``."""
        data = bytes(payload)
        self._put(_Item(TOPIC_TELEGRAM, t_ns, lambda: data, encoding=f"sick-cola-{dialect}"))

    def log_scan(
        self,
        t_ns: int,
        ranges_m: ArrayLike,
        start_alpha: float,
        end_alpha: float,
        intensities: ArrayLike | None = None,
    ) -> None:
        """A decoded scan as ``foxglove.LaserScan`` in frame ``scan_plane`` (angles are alpha)."""
        r = np.asarray(ranges_m, dtype=np.float64)
        inten = None if intensities is None else np.asarray(intensities, dtype=np.float64)

        def build() -> bytes:
            msg = LaserScan()
            _stamp(msg.timestamp, t_ns)
            msg.frame_id = "scan_plane"
            msg.pose.orientation.w = 1.0
            msg.start_angle = float(start_alpha)
            msg.end_angle = float(end_alpha)
            # ranges and intensities are the last fields: append them packed straight from numpy
            # (the library's own encoding, 40x faster than extending the repeated field)
            head = bytes(msg.SerializeToString())
            tail = _packed_doubles(_RANGES_TAG, r)
            if inten is not None:
                tail += _packed_doubles(_INTENSITIES_TAG, inten)
            return head + tail

        self._put(_Item(TOPIC_SCAN, t_ns, build))

    def log_motor(self, t_ns: int, position_rad: float, velocity_rad_s: float, name: str = "tilt") -> None:
        """One timestamped motor sample (``t_ns`` is the sample's host time) as ``foxglove.JointStates``."""

        def build() -> bytes:
            msg = JointStates()
            _stamp(msg.timestamp, t_ns)
            j = msg.joints.add()
            j.name = name
            j.position = float(position_rad)
            j.velocity = float(velocity_rad_s)
            return bytes(msg.SerializeToString())

        self._put(_Item(TOPIC_MOTOR, t_ns, build))

    def log_plane_pose(self, t_ns: int, beta: float, p: float) -> None:
        """``rig -> scan_plane`` at motor angle ``beta`` (rad) with inner parameter ``p`` (m)."""
        trans = (p * np.cos(beta), 0.0, p * np.sin(beta))
        rot = plane_rotation(beta)
        self._put(_Item(TOPIC_TF, t_ns, lambda: _transform(t_ns, "rig", "scan_plane", rot, trans)))

    def log_world_pose(self, t_ns: int, world_from_rig: ArrayLike) -> None:
        t = np.asarray(world_from_rig, dtype=np.float64)
        self._put(_Item(TOPIC_TF, t_ns, lambda: _transform(t_ns, "world", "rig", t[:3, :3], t[:3, 3])))

    def log_cloud(self, t_ns: int, points: ArrayLike, frame_id: str = "world") -> None:
        """The mapped cloud as ``foxglove.PointCloud`` (float32 x, y, z)."""
        pts = np.ascontiguousarray(np.asarray(points, dtype=np.float32).reshape(-1, 3))

        def build() -> bytes:
            msg = PointCloud()
            _stamp(msg.timestamp, t_ns)
            msg.frame_id = frame_id
            msg.pose.orientation.w = 1.0
            msg.point_stride = 12
            for i, name in enumerate("xyz"):
                f = msg.fields.add()
                f.name = name
                f.offset = 4 * i
                f.type = PackedElementField.FLOAT32
            msg.data = pts.tobytes()
            return bytes(msg.SerializeToString())

        self._put(_Item(TOPIC_CLOUD, t_ns, build))

    def log_json(self, topic: str, t_ns: int, obj: Any) -> None:
        """A JSON message on one of the ``/lrms/*`` topics."""
        if topic not in _JSON_SCHEMA:
            raise McapLogError(f"{topic!r} is not a JSON topic of the raw log")
        data = json.dumps(json_safe(obj), allow_nan=False).encode()
        self._put(_Item(topic, t_ns, lambda: data))

    def close(self) -> None:
        """Drain the queue, write the summary and close the file; re-raise a writer failure."""
        with self._lock:
            if not self._closed:
                self._closed = True
                self._q.put(_STOP)
                self._thread.join()
        if self._error is not None:
            raise McapLogError(f"raw log {self.path} failed: {self._error}") from self._error

    def __enter__(self) -> McapLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- writer thread --------------------------------------------------------------------
    def _channel(self, topic: str, encoding: str) -> int:
        key = (topic, encoding)
        cid = self._channels.get(key)
        if cid is not None:
            return cid
        if topic in _PROTO:
            cls = _PROTO[topic]
            sid = self._writer.register_schema(
                name=cls.DESCRIPTOR.full_name,
                encoding="protobuf",
                data=build_file_descriptor_set(cls).SerializeToString(),
            )
            cid = self._writer.register_channel(topic=topic, message_encoding="protobuf", schema_id=sid)
        elif topic in _JSON_SCHEMA:
            doc: dict[str, Any] = {"type": "object", "title": _JSON_SCHEMA[topic]}
            if topic in _JSON_PROPERTIES:
                doc["properties"] = _JSON_PROPERTIES[topic]
            schema = json.dumps(doc).encode()
            sid = self._writer.register_schema(name=_JSON_SCHEMA[topic], encoding="jsonschema", data=schema)
            cid = self._writer.register_channel(topic=topic, message_encoding="json", schema_id=sid)
        else:
            cid = self._writer.register_channel(topic=topic, message_encoding=encoding, schema_id=0)
        self._channels[key] = cid
        return cid

    def _run(self) -> None:
        last_flush = time.monotonic()
        dirty = False
        seq = 0
        try:
            while True:
                try:
                    item = self._q.get(timeout=self._flush_interval)
                except queue.Empty:
                    item = None
                if item is _STOP:
                    break
                if isinstance(item, _Item):
                    cid = self._channel(item.topic, item.encoding)
                    self._writer.add_message(
                        channel_id=cid, log_time=item.t_ns, publish_time=item.t_ns, data=item.build(), sequence=seq
                    )
                    seq += 1
                    self.messages_written += 1
                    dirty = True
                now = time.monotonic()
                if dirty and now - last_flush >= self._flush_interval:
                    self._writer.flush()
                    self._fh.flush()
                    self.messages_flushed = self.messages_written
                    self.flushes += 1
                    last_flush = now
                    dirty = False
            self._writer.finish()
        except BaseException as exc:  # keep the failure for the producer side
            self._error = exc
            # drain so that producers blocked on nothing keep working; they see _error
        finally:
            try:
                self._fh.close()
            except OSError as exc:
                self._error = self._error or exc


# -- reading ------------------------------------------------------------------------------


@dataclass(frozen=True)
class LoggedMessage:
    topic: str
    schema_name: str
    encoding: str
    log_time_ns: int
    data: bytes

    def decode(self) -> Any:
        """A protobuf message, a JSON value, or the raw bytes."""
        if self.encoding == "protobuf":
            cls = _PROTO_BY_NAME.get(self.schema_name)
            if cls is None:
                raise McapLogError(f"unknown protobuf schema {self.schema_name!r} on {self.topic}")
            msg = cls()
            msg.ParseFromString(self.data)
            return msg
        if self.encoding == "json":
            return json.loads(self.data)
        return self.data


@dataclass
class LogReadStatus:
    messages: int = 0
    truncated: bool = False
    reason: str = ""


def iter_log(path: str | Path | BinaryIO, status: LogReadStatus | None = None) -> Iterator[LoggedMessage]:
    """Every message of a raw log in file order, also from a file cut short by a crash.

    A complete file and a truncated one read the same way: messages of every complete chunk,
    then a stop where the file ends. ``status.truncated`` tells which case it was. ``path`` may
    also be an open binary file (read from its start, left open): a log fetched from an archive
    (``lrms reprocess`` reads through fsspec).
    """
    st = status if status is not None else LogReadStatus()
    owned = isinstance(path, str | Path)
    if isinstance(path, str | Path):
        try:
            fh: BinaryIO = open(path, "rb")  # noqa: SIM115
        except OSError as exc:
            raise McapLogError(f"cannot open raw log {path}: {exc.strerror or exc}") from None
    else:
        fh = path
        fh.seek(0)
        path = str(getattr(fh, "name", "") or "(raw log stream)")
    with fh if owned else contextlib.nullcontext(fh):
        if fh.read(8) != MCAP_MAGIC:
            raise McapLogError(f"{path} is not an MCAP file")
        fh.seek(0)
        reader = NonSeekingReader(fh)
        it = reader.iter_messages(log_time_order=False)
        while True:
            try:
                schema, channel, message = next(it)
            except StopIteration:
                return
            except (McapError, struct.error, EOFError, ValueError) as exc:
                if st.messages == 0 and isinstance(exc, InvalidMagic):
                    raise McapLogError(f"{path} is not an MCAP file") from None
                st.truncated = True
                st.reason = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
                return
            except Exception as exc:  # zstd/lz4 errors on a chunk cut mid-way
                st.truncated = True
                st.reason = f"{type(exc).__name__}: {exc}"
                return
            st.messages += 1
            yield LoggedMessage(
                topic=channel.topic,
                schema_name=schema.name if schema is not None else "",
                encoding=channel.message_encoding,
                log_time_ns=message.log_time,
                data=message.data,
            )


def read_log(path: str | Path) -> tuple[list[LoggedMessage], LogReadStatus]:
    status = LogReadStatus()
    msgs = list(iter_log(path, status))
    return msgs, status
