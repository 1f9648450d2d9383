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
        """The next message that is not a scan event (events are kept in ``self.events``)."""
        while True:
            msg = self._next()
            if isinstance(msg, ScanDataEvent):
                self.events.append(msg.scan)
                continue
            return msg

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
