"""Fixtures for the simulator tests: a plain-socket CoLa client (the codec's client side, no driver)."""

from __future__ import annotations

import socket
from collections.abc import Iterator

import pytest

from drivers.lms100 import CoLaConnection, Message, Scan, ScanDataEvent


class Link:
    """A TCP connection speaking CoLa through :class:`CoLaConnection` (client role)."""

    def __init__(self, address: tuple[str, int], dialect: str) -> None:
        self.sock = socket.create_connection(address, timeout=10)
        self.conn = CoLaConnection(dialect, role="client")
        self.events: list[Scan] = []
        self.other_events: list[Message] = []
        """``sSN`` events other than scans (LIDoutputstate, LIDinputstate), in arrival order."""

    def _next(self) -> Message:
        while True:
            msg = self.conn.next_message()
            if msg is not None:
                return msg
            data = self.sock.recv(65536)
            if not data:
                raise ConnectionError("device closed the connection")
            self.conn.receive_data(data)

    def send_raw(self, data: bytes) -> None:
        self.sock.sendall(data)

    def reply(self) -> Message:
        """The next message that is not an event (scans are kept in ``self.events``, others in ``other_events``)."""
        while True:
            msg = self._next()
            if isinstance(msg, ScanDataEvent):
                self.events.append(msg.scan)
                continue
            if msg.kind == "sSN":
                self.other_events.append(msg)
                continue
            return msg

    def event(self) -> Message:
        """The next ``sSN`` event other than a scan (scans that arrive meanwhile go to ``self.events``)."""
        while not self.other_events:
            msg = self._next()
            if isinstance(msg, ScanDataEvent):
                self.events.append(msg.scan)
            elif msg.kind == "sSN":
                self.other_events.append(msg)
            else:
                raise AssertionError(f"expected an event, got {msg!r}")
        return self.other_events.pop(0)

    def request(self, msg: Message) -> Message:
        self.sock.sendall(self.conn.send(msg))
        return self.reply()

    def scans(self, n: int) -> list[Scan]:
        """The next ``n`` streamed scans (starting with any already buffered)."""
        while len(self.events) < n:
            msg = self._next()
            if isinstance(msg, ScanDataEvent):
                self.events.append(msg.scan)
        out, self.events = self.events[:n], self.events[n:]
        return out

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def connect() -> Iterator[object]:
    links: list[Link] = []

    def make(address: tuple[str, int], dialect: str = "b") -> Link:
        link = Link(address, dialect)
        links.append(link)
        return link

    yield make
    for link in links:
        link.close()
