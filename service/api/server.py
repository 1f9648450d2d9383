"""Run the app with uvicorn, in the foreground (``lrms serve``) or on a background thread (tests, bench)."""

from __future__ import annotations

import threading
import time

import uvicorn
from fastapi import FastAPI

from service.errors import ServiceError


class ServerThread:
    """uvicorn on ``host:port`` (port 0 = an ephemeral port) in a daemon thread."""

    def __init__(self, app: FastAPI, host: str = "127.0.0.1", port: int = 0, log_level: str = "warning") -> None:
        config = uvicorn.Config(app, host=host, port=port, log_level=log_level, lifespan="on", access_log=False)
        self.server = uvicorn.Server(config)
        self._thread = threading.Thread(target=self.server.run, name="lrms-http", daemon=True)
        self.host = host
        self.port = 0

    def start(self, timeout: float = 20.0) -> ServerThread:
        self._thread.start()
        end = time.monotonic() + timeout
        while not self.server.started:
            if not self._thread.is_alive():
                raise ServiceError("the HTTP server stopped while starting (port in use?)")
            if time.monotonic() > end:
                raise ServiceError("the HTTP server did not start in time")
            time.sleep(0.01)
        sock = self.server.servers[0].sockets[0]
        self.port = int(sock.getsockname()[1])
        return self

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def stop(self, timeout: float = 30.0) -> None:
        self.server.should_exit = True
        self._thread.join(timeout)

    def __enter__(self) -> ServerThread:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
