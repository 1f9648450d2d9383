"""The REST API of the acquisition service (FastAPI).

The names below load on first use (PEP 562): ``from service.api import Service`` imports only
:mod:`service.api.core` (the store, job runner and scheduler; no FastAPI app, routes or uvicorn),
which is all the embedded ``lrms measure`` needs; ``create_app`` loads the app and its routes,
``ServerThread`` uvicorn.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from service.api.app import create_app
    from service.api.core import Service
    from service.api.server import ServerThread

__all__ = ["ServerThread", "Service", "create_app"]

_WHERE = {"create_app": "service.api.app", "Service": "service.api.core", "ServerThread": "service.api.server"}


def __getattr__(name: str) -> Any:
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_WHERE])
