"""FastAPI dependencies of the routes: the :class:`Service` behind the app and the role checks.

``READ``, ``OPERATE`` and ``ADMIN`` are route (or router) dependency lists: a bearer token of at
least that role (:mod:`service.api.auth`); ``READ`` passes everyone when ``[auth] read = "open"``.
``*_RESPONSES`` declare the status codes they add to a route's OpenAPI entry.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.api import auth
from service.api.core import Service
from service.api.errors import responses
from service.config import Role

_bearer = HTTPBearer(auto_error=False)


def get_service(request: Request) -> Service:
    """The :class:`Service` the app was built around (``create_app`` puts it in ``app.state``)."""
    svc: Service = request.app.state.service
    return svc


ServiceDep = Annotated[Service, Depends(get_service)]
Credentials = Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]


def _require(service: Service, creds: HTTPAuthorizationCredentials | None, need: Role) -> None:
    token = creds.credentials if creds is not None and creds.scheme.lower() == "bearer" else None
    try:
        auth.check(service.config, token or None, need)
    except auth.Denied as exc:
        raise HTTPException(exc.status, exc.detail, headers=exc.headers or None) from None


def require_read(service: ServiceDep, creds: Credentials) -> None:
    """Reads: a read, operator or admin token when ``[auth] read = "token"``; nothing when open."""
    _require(service, creds, "read")


def require_operator(service: ServiceDep, creds: Credentials) -> None:
    """Start and cancel measurements: the operator or admin token."""
    _require(service, creds, "operator")


def require_admin(service: ServiceDep, creds: Credentials) -> None:
    """Schedules (and any configuration, calibration or deletion endpoint): the admin token."""
    _require(service, creds, "admin")


READ = [Depends(require_read)]
OPERATE = [Depends(require_operator)]
ADMIN = [Depends(require_admin)]
READ_RESPONSES = responses(401, 403)
WRITE_RESPONSES = responses(401, 403, 413)
