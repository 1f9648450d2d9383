"""A raw log cut short by a crash, made whole again: the records that can be read, rewritten with
a summary and index, so that indexed readers (Foxglove, ``mcap``'s ``make_reader``) accept it.

The service calls :func:`recover_log` on restart for the log of each measurement a dead process
left running (:meth:`service.jobs.JobRunner.start`); the log is then served as truncated.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import os
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from mcap.reader import make_reader
from mcap.records import Attachment, Channel, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from service.mcaplog import MCAP_MAGIC, McapLogError, read_log

#: Name of the MCAP metadata record :func:`recover_log` adds to a log it rebuilt from a truncated file.
RECOVERY_METADATA = "lrms.recovery"


@dataclass(frozen=True)
class Recovery:
    """What :func:`recover_log` found: ``truncated`` False means the file was complete already."""

    messages: int
    truncated: bool
    first_ns: int | None = None
    last_ns: int | None = None
    reason: str = ""

    def describe(self) -> str:
        """One line for a measurement's error: where the log ends and how much of it was kept."""
        if self.last_ns is None or self.first_ns is None:
            return "its raw log had no complete chunk: nothing was recovered"
        at = dt.datetime.fromtimestamp(self.last_ns / 1e9, tz=dt.UTC).isoformat(timespec="milliseconds")
        span = (self.last_ns - self.first_ns) / 1e9
        return (
            f"the raw log is truncated at {at.replace('+00:00', 'Z')} ({span:.1f} s after it began): "
            f"{self.messages} messages recovered"
        )


def has_summary(path: str | Path) -> bool:
    """Whether ``path`` is a complete MCAP file (footer and summary: indexed readers accept it)."""
    try:
        with open(path, "rb") as fh:
            return make_reader(fh).get_summary() is not None
    except Exception:  # the library raises many kinds on a cut file; any of them means "not complete"
        return False


def recover_log(path: str | Path, compression: str = "zstd") -> Recovery:
    """Make a raw log cut short by a crash complete: every readable record (header, schemas,
    channels, messages, metadata, attachments) of every complete chunk is written through a new
    :class:`~mcap.writer.Writer` into ``PATH.recovering``, which gets a summary, index and a
    :data:`RECOVERY_METADATA` record, is synced, and then atomically replaces ``path``.

    A file that already has its summary is left as it is (``truncated`` False); a file with no
    complete message is left too (``messages`` 0). Reading stops at the first record that cannot be
    read (the cut); CRCs of chunks are checked, so a damaged chunk ends the recovery there.
    """
    src = Path(path)
    if has_summary(src):
        msgs, status = read_log(src)
        times = [m.log_time_ns for m in msgs]
        return Recovery(len(msgs), status.truncated, min(times, default=None), max(times, default=None))
    try:
        fh = open(src, "rb")  # noqa: SIM115
    except OSError as exc:
        raise McapLogError(f"cannot open raw log {src}: {exc.strerror or exc}") from None
    comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[compression]
    tmp = src.with_name(src.name + ".recovering")
    n = 0
    first: int | None = None
    last: int | None = None
    reason = "end of file"
    with fh:
        head = fh.read(8)
        if len(head) < 8 and MCAP_MAGIC.startswith(head):  # killed before the first write reached the file
            return Recovery(0, True, reason="the file ends before the MCAP magic")
        if head != MCAP_MAGIC:
            raise McapLogError(f"{src} is not an MCAP file")
        fh.seek(0)
        records = StreamReader(fh, validate_crcs=True).records
        with open(tmp, "wb") as out:
            writer = Writer(out, compression=comp)
            started = False
            schemas: dict[int, int] = {}
            channels: dict[int, int] = {}
            while True:
                try:
                    rec = next(records)
                except StopIteration:
                    break
                except Exception as exc:  # the cut: short read, struct/zstd/CRC errors
                    reason = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
                    break
                if isinstance(rec, Footer):
                    break
                if not started:
                    if isinstance(rec, Header):
                        writer.start(profile=rec.profile, library=rec.library)
                        started = True
                        continue
                    writer.start(profile="", library="lrms")
                    started = True
                if isinstance(rec, Schema) and rec.id not in schemas:
                    schemas[rec.id] = writer.register_schema(name=rec.name, encoding=rec.encoding, data=rec.data)
                elif isinstance(rec, Channel) and rec.id not in channels:
                    channels[rec.id] = writer.register_channel(
                        topic=rec.topic,
                        message_encoding=rec.message_encoding,
                        schema_id=schemas.get(rec.schema_id, 0),
                        metadata=dict(rec.metadata),
                    )
                elif isinstance(rec, Message) and rec.channel_id in channels:
                    writer.add_message(
                        channel_id=channels[rec.channel_id],
                        log_time=rec.log_time,
                        publish_time=rec.publish_time,
                        data=rec.data,
                        sequence=rec.sequence,
                    )
                    n += 1
                    first = rec.log_time if first is None else min(first, rec.log_time)
                    last = rec.log_time if last is None else max(last, rec.log_time)
                elif isinstance(rec, Metadata):
                    writer.add_metadata(rec.name, dict(rec.metadata))
                elif isinstance(rec, Attachment):
                    writer.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data)
            if not started:
                writer.start(profile="", library="lrms")
            result = Recovery(n, True, first, last, reason)
            writer.add_metadata(
                RECOVERY_METADATA,
                {
                    "messages": str(n),
                    "first_log_time_ns": "" if first is None else str(first),
                    "last_log_time_ns": "" if last is None else str(last),
                    "source_bytes": str(src.stat().st_size),
                    "stopped_at": reason,
                    "note": "rebuilt from a raw log whose writer was killed; later data was lost",
                },
            )
            writer.finish()
            out.flush()
            os.fsync(out.fileno())
    if n == 0:
        tmp.unlink()
        return result
    os.replace(tmp, src)
    return result


def recovery_info(path: str | Path | BinaryIO) -> dict[str, str] | None:
    """The :data:`RECOVERY_METADATA` record of a log :func:`recover_log` rebuilt, else None
    (``path`` may be an open, seekable binary file, left open)."""
    try:
        with open(path, "rb") if isinstance(path, str | Path) else contextlib.nullcontext(path) as fh:
            fh.seek(0)
            for record in make_reader(fh).iter_metadata():
                if record.name == RECOVERY_METADATA:
                    return dict(record.metadata)
    except Exception:  # no summary (a truncated file) or not MCAP: not a recovered log
        return None
    return None
