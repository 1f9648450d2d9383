"""The body guard: a pure ASGI middleware that decides on a request's headers before its body is read.

FastAPI reads and parses a JSON body before a route's dependencies run, so without this an
unauthenticated 40 MB POST is parsed in full (in the event loop) before the token check refuses it.
The guard runs first:

* POST, PUT and PATCH need a bearer token of the operator or admin role (every endpoint with a
  body writes); anything else is answered 401/403 at once, from the headers, with
  ``Connection: close`` so the server does not read the body it refused. Finer role checks (admin
  for schedules) stay in the route dependencies (:mod:`service.api.deps`).
* Every request body is limited to ``[api] max_body_bytes``: a larger ``Content-Length`` is
  answered 413 at once; a body without one (``Transfer-Encoding: chunked``) is read into a buffer
  that never holds more than the limit, answered 413 as soon as it would, and otherwise handed to
  the app in one piece.
"""

from __future__ import annotations

import json
from typing import Any

from service.api import auth
from service.api.core import Service

BODY_METHODS = frozenset({"POST", "PUT", "PATCH"})

Scope = dict[str, Any]
Message = dict[str, Any]


async def reply(send: Any, status: int, detail: str, headers: dict[str, str] | None = None, close: bool = True) -> None:
    """A JSON ``{"detail": ...}`` response; ``close``: the server then closes the connection, so the
    unread rest of a refused body is never read (a client still sending gets a broken pipe, and
    then reads this answer, as curl and httpx do)."""
    body = json.dumps({"detail": detail}).encode()
    raw = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    if close:
        raw.append((b"connection", b"close"))
    raw += [(k.lower().encode(), v.encode()) for k, v in (headers or {}).items()]
    await send({"type": "http.response.start", "status": status, "headers": raw})
    await send({"type": "http.response.body", "body": body, "more_body": False})


class BodyGuard:
    """See the module docstring. ``service.config`` gives the tokens and the body limit."""

    def __init__(self, app: Any, service: Service) -> None:
        self.app = app
        self.service = service
        self.refused = 0
        """Requests answered by the guard itself (401, 403, 413, 400), for tests and diagnostics."""

    async def __call__(self, scope: Scope, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        authorization: str | None = None
        length: bytes | None = None
        chunked = False
        for name, value in scope["headers"]:
            if name == b"authorization":
                authorization = value.decode("latin-1")
            elif name == b"content-length":
                length = value
            elif name == b"transfer-encoding":
                chunked = True
        config = self.service.config
        if scope["method"] in BODY_METHODS:
            try:
                auth.check(config, auth.bearer(authorization), "operator")
            except auth.Denied as exc:
                self.refused += 1
                has_body = chunked or (length is not None and length.strip() not in (b"", b"0"))
                await reply(send, exc.status, exc.detail, exc.headers, close=has_body)
                return
        limit = config.api.max_body_bytes
        if length is not None:
            try:
                n = int(length)
            except ValueError:
                n = -1
            if n < 0:
                self.refused += 1
                await reply(send, 400, "invalid Content-Length header")
                return
            if n > limit:
                self.refused += 1
                await reply(send, 413, f"request body of {n} bytes exceeds the limit of {limit} bytes")
                return
            await self.app(scope, receive, send)
            return
        if not chunked:
            await self.app(scope, receive, send)
            return
        body = bytearray()
        while True:
            message: Message = await receive()
            if message["type"] == "http.disconnect":
                return
            chunk = message.get("body", b"")
            if len(body) + len(chunk) > limit:
                self.refused += 1
                await reply(send, 413, f"request body exceeds the limit of {limit} bytes")
                return
            body += chunk
            if not message.get("more_body", False):
                break
        await self.app(scope, _replay(bytes(body), receive), send)


def _replay(body: bytes, receive: Any) -> Any:
    """A ``receive`` that hands over ``body`` in one message, then waits on the real one (disconnect)."""
    done = False

    async def replayed() -> Message:
        nonlocal done
        if not done:
            done = True
            return {"type": "http.request", "body": body, "more_body": False}
        message: Message = await receive()
        return message

    return replayed
