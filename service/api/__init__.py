"""The REST API of the acquisition service (FastAPI)."""

from service.api.app import Service, create_app
from service.api.server import ServerThread

__all__ = ["ServerThread", "Service", "create_app"]
