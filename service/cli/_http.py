"""The CLI's HTTP client of a running ``lrms serve`` (``lrms measure --server``, ``lrms report``).

Standard library only (``urllib``; no numpy, pydantic or HTTP client library), so a command that
uses it starts in the interpreter's time. Every failure is a :class:`ServiceError` with one clear
line: the service unreachable, its refusal (the status and the error body's message), a reply that
is not the API's (not JSON, cut short, a read timeout), a download that could not be written.
Downloads go to a temporary file beside the target, renamed onto it only once complete, so a
failed download leaves no half-written file.
"""

from __future__ import annotations

import contextlib
import http.client
import json
import os
import tempfile
import urllib.error
import urllib.request
from collections.abc import Sequence
from typing import Any

from service.errors import ServiceError

#: What a body read can raise: a socket error or read timeout (``OSError``), a reply cut short
#: (``http.client.IncompleteRead``, an ``HTTPException``), a body that is not JSON (``ValueError``).
_READ_ERRORS = (OSError, http.client.HTTPException, ValueError)
#: Bytes per read of a download.
_CHUNK = 1 << 16


def token_from(given: str | None, env_vars: Sequence[str]) -> str | None:
    """``given`` (a ``--token``), else the first of ``env_vars`` set and non-empty, else None."""
    return given or next((os.environ[v] for v in env_vars if os.environ.get(v)), None)


def error_detail(raw: bytes, reason: str) -> str:
    """An error body's message: ``message`` (a 422's summary), else ``detail``, else its text
    (200 characters), else ``reason`` (the status line's)."""
    try:
        body = json.loads(raw)
    except ValueError:
        return raw.decode(errors="replace")[:200] or reason
    if isinstance(body, dict):
        return str(body.get("message") or body.get("detail") or body)
    return str(body)


class ApiClient:
    """Requests to the service at ``base`` with an optional bearer token; ``timeout`` seconds for
    the connection and for each read."""

    def __init__(self, base: str, token: str | None, timeout: float) -> None:
        if not timeout > 0:
            raise ServiceError(f"--timeout must be positive, got {timeout}")
        self.base = base.rstrip("/")
        self.headers = {"Accept": "application/json"}
        if token:
            self.headers["Authorization"] = f"Bearer {token}"
        self.timeout = timeout

    def open(self, method: str, path: str, body: dict[str, Any] | None = None) -> Any:
        """The response of ``method path`` (a file-like object); HTTP errors as :class:`ServiceError`."""
        headers = dict(self.headers)
        data = None
        if body is not None:
            data = json.dumps(body).encode()
            headers["Content-Type"] = "application/json"
        req = urllib.request.Request(self.base + path, data=data, headers=headers, method=method)
        try:
            return urllib.request.urlopen(req, timeout=self.timeout)
        except urllib.error.HTTPError as exc:
            try:
                raw = exc.read()
            except _READ_ERRORS:
                raw = b""
            detail = error_detail(raw, str(exc.reason))
            raise ServiceError(f"the service answered {exc.code} to {method} {path}: {detail}") from None
        except (urllib.error.URLError, OSError, http.client.HTTPException) as exc:
            reason = getattr(exc, "reason", None) or exc
            raise ServiceError(f"cannot reach the service at {self.base}: {reason}") from None

    def _bad(self, method: str, path: str, exc: BaseException) -> ServiceError:
        what = type(exc).__name__ if not str(exc) else f"{type(exc).__name__}: {str(exc)[:120]}"
        return ServiceError(f"the reply to {method} {path} from {self.base} is not an lrms API answer ({what})")

    def json(self, method: str, path: str, body: dict[str, Any] | None = None) -> dict[str, Any]:
        """The JSON object answered to ``method path``."""
        with self.open(method, path, body) as r:
            try:
                out = json.load(r)
            except _READ_ERRORS as exc:
                raise self._bad(method, path, exc) from None
        if not isinstance(out, dict):
            raise self._bad(method, path, ValueError(f"a JSON {type(out).__name__}, not an object"))
        return out

    def read(self, path: str) -> bytes:
        """The whole body answered to ``GET path``."""
        with self.open("GET", path) as r:
            try:
                data: bytes = r.read()
            except _READ_ERRORS as exc:
                raise self._bad("GET", path, exc) from None
        return data

    def download(self, path: str, dest: str) -> None:
        """``GET path`` into the file ``dest``, replaced only once the body is complete."""
        folder = os.path.dirname(os.path.abspath(dest))
        try:
            fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(dest)}.", suffix=".part", dir=folder)
        except OSError as exc:
            raise ServiceError(f"cannot write {dest}: {exc}") from None
        mask = os.umask(0)  # the file's mode as open() would make it, not mkstemp's 0600
        os.umask(mask)
        os.chmod(tmp, 0o666 & ~mask)
        try:
            with os.fdopen(fd, "wb") as f, self.open("GET", path) as r:
                while True:
                    try:
                        chunk = r.read(_CHUNK)
                    except _READ_ERRORS as exc:
                        raise self._bad("GET", path, exc) from None
                    if not chunk:
                        break
                    try:
                        f.write(chunk)
                    except OSError as exc:
                        raise ServiceError(f"cannot write {dest}: {exc}") from None
            try:
                os.replace(tmp, dest)
            except OSError as exc:
                raise ServiceError(f"cannot write {dest}: {exc}") from None
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise
