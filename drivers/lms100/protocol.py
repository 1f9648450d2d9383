"""h11-style CoLa connection state: bytes in, messages out, and back. No I/O.

>>> dev = CoLaConnection(Dialect.B, role="device")
>>> cli = CoLaConnection(Dialect.B, role="client")
>>> dev.receive_data(cli.send(PollScan()))
>>> dev.next_message()
PollScan()
"""

from __future__ import annotations

from typing import Literal

from drivers.lms100.errors import TelegramError
from drivers.lms100.framing import DEFAULT_MAX_PAYLOAD, Dialect, Framer, frame
from drivers.lms100.messages import REPLY_KINDS, REQUEST_KINDS, Message, PollScan, decode_payload

Role = Literal["client", "device"]

__all__ = ["CoLaConnection", "PollScan", "Role"]


class CoLaConnection:
    """One end of a CoLa link.

    ``role="client"`` sends requests (sRN/sWN/sMN/sEN) and receives replies and events;
    ``role="device"`` does the opposite. :meth:`send` returns the framed bytes to write;
    :meth:`receive_data` takes whatever arrived (any chunking); :meth:`next_message` returns the
    next decoded message or ``None`` when more bytes are needed. A broken frame raises
    :class:`~drivers.lms100.errors.FramingError`, an unparseable one or one of the wrong direction
    :class:`~drivers.lms100.errors.TelegramError`; either way the offending telegram is gone and
    the connection stays usable.
    """

    def __init__(self, dialect: Dialect | str, role: Role, max_payload: int = DEFAULT_MAX_PAYLOAD) -> None:
        if role not in ("client", "device"):
            raise ValueError(f"role must be 'client' or 'device', not {role!r}")
        self.dialect = Dialect(dialect)
        self.role: Role = role
        self._framer = Framer(self.dialect, max_payload)
        self._out_kinds = REQUEST_KINDS if role == "client" else REPLY_KINDS
        self._in_kinds = REPLY_KINDS if role == "client" else REQUEST_KINDS
        self.messages_sent = 0
        self.messages_received = 0

    @property
    def framer(self) -> Framer:
        """The underlying framer (its ``skipped_bytes``/``errors`` counters are useful diagnostics)."""
        return self._framer

    def send(self, msg: Message) -> bytes:
        """Framed bytes for ``msg``. A client may only send requests, a device only replies/events."""
        if msg.kind not in self._out_kinds:
            raise TelegramError(f"a {self.role} does not send {msg.kind} telegrams")
        data = frame(msg.encode(self.dialect), self.dialect)
        self.messages_sent += 1
        return data

    def receive_data(self, data: bytes | bytearray | memoryview) -> None:
        """Hand over received bytes (an empty chunk is allowed and ignored)."""
        if data:
            self._framer.feed(data)

    def next_message(self) -> Message | None:
        """The next received message, or None if a complete telegram has not arrived yet."""
        payload = self._framer.next_payload()
        if payload is None:
            return None
        msg = decode_payload(payload, self.dialect)
        if msg.kind not in self._in_kinds:
            raise TelegramError(f"a {self.role} does not expect {msg.kind} telegrams ({msg.kind} {msg.name})")
        self.messages_received += 1
        return msg

    def messages(self) -> list[Message]:
        """All complete messages received so far (raises on the first bad telegram, like next_message)."""
        out: list[Message] = []
        while (msg := self.next_message()) is not None:
            out.append(msg)
        return out
