"""The REST API of the acquisition service (FastAPI)."""

from service.api.app import create_app
from service.api.core import Service
from service.api.server import ServerThread

__all__ = ["ServerThread", "Service", "create_app"]
