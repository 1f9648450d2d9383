"""The REST API's error bodies, the one place their status codes are declared, and the handlers
that produce them.

Two body formats, both pydantic models and both in the OpenAPI schema:

* :class:`ErrorBody` ``{"detail": "..."}`` for 400, 401, 403, 404, 405, 409, 413, 429 and 503;
* :class:`ValidationErrorBody` ``{"message": "...", "detail": [{"loc": [...], "msg": "...",
  "type": "..."}]}`` for every 422, whether the request's schema refused it (FastAPI's
  ``RequestValidationError``), the rig refused it (:class:`service.errors.RequestFieldError`: travel
  limits, maximum speed, planned duration, a schedule's minimum interval) or a route raised
  ``HTTPException(422)``. The input values are not echoed (a non-finite number cannot be written
  as JSON).

A route declares what it may answer in one line: ``responses=responses(401, 403, 404)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from service.errors import RequestFieldError, ServiceError
from service.jobs import QueueFull
from service.store import NotFound, StoreError


class ErrorBody(BaseModel):
    """Every error but 422."""

    detail: str = Field(description="what went wrong")


class FieldError(BaseModel):
    """One refused field."""

    loc: list[str | int] = Field(
        description='where: "body", "query" or "path", then the field names (and list indices), '
        'e.g. ["body", "sweep", "speed_deg_s"]'
    )
    msg: str = Field(description="why")
    type: str = Field(
        description='pydantic\'s error type ("greater_than_equal", "finite_number", ...), '
        'or "value_error" for a check against the rig'
    )


class ValidationErrorBody(BaseModel):
    """A 422: the request was refused; every refused field is named."""

    message: str = Field(description='all of detail in one line: "body.sweep.speed_deg_s: ...; ..."')
    detail: list[FieldError]


_DESCRIPTIONS: dict[int, str] = {
    400: "the request body could not be read (not UTF-8 JSON)",
    401: "no bearer token, or an unknown one",
    403: "the token's role may not do this (read < operator < admin), or no token of the needed role is configured",
    404: "no measurement, schedule or calibration with this id (or no active calibration), "
    "no recipe (or recipe version) of this name",
    409: "the measurement's state does not allow this: cancel a finished one; its raw log or cloud while it "
    "runs, or when it has none (cancelled before it ran, failed before anything was recorded); a recipe that "
    "exists already; a control chart of fewer than 2 parts",
    413: "the request body is larger than [api] max_body_bytes (refused before it is read)",
    422: "the request was refused: every refused field with the reason",
    429: "the measurement queue is full; retry after Retry-After seconds",
    503: "the service is up but cannot measure (rig process or drive not ready); the body says why",
}

_HEADERS: dict[int, dict[str, Any]] = {
    401: {"WWW-Authenticate": {"description": "Bearer", "schema": {"type": "string"}}},
    429: {"Retry-After": {"description": "seconds to wait before retrying", "schema": {"type": "integer"}}},
}


def responses(*codes: int, **models: type[BaseModel]) -> dict[int | str, dict[str, Any]]:
    """The OpenAPI ``responses`` of a route for the error ``codes`` it may answer (``responses(401,
    404)``); ``models`` replaces a code's body model (``responses(503, _503=HealthOut)``)."""
    out: dict[int | str, dict[str, Any]] = {}
    for code in codes:
        if code not in _DESCRIPTIONS:
            raise ValueError(f"no documented error body for status {code}")
        model: type[BaseModel] = models.get(f"_{code}", ValidationErrorBody if code == 422 else ErrorBody)
        entry: dict[str, Any] = {"model": model, "description": _DESCRIPTIONS[code]}
        if code in _HEADERS:
            entry["headers"] = _HEADERS[code]
        out[code] = entry
    return out


def validation_response(errors: Sequence[tuple[Sequence[str | int], str, str]]) -> JSONResponse:
    """A 422 with ``(loc, msg, type)`` items in the one format."""
    items = [FieldError(loc=list(loc), msg=msg, type=kind) for loc, msg, kind in errors]
    message = "; ".join(f"{'.'.join(str(x) for x in i.loc)}: {i.msg}" if i.loc else i.msg for i in items)
    body = ValidationErrorBody(message=message, detail=items)
    return JSONResponse(status_code=422, content=body.model_dump(mode="json"))


_METHODS = ("DELETE", "GET", "HEAD", "OPTIONS", "PATCH", "POST", "PUT")


def _allowed_methods(request: Request) -> str:
    """Every method some route of the app answers at this path (the router's 405 names only the
    methods of the first route whose path matched). Asked of the router itself, method by method,
    so routes of included routers count too."""
    allowed = []
    for method in _METHODS:
        scope = {**request.scope, "method": method}
        if any(route.matches(scope)[0] is Match.FULL for route in request.app.router.routes):
            allowed.append(method)
    return ", ".join(allowed)


def install_handlers(app: FastAPI) -> None:
    """Register the handlers that give every error its documented body."""

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        return validation_response(
            [
                (
                    tuple(e.get("loc", ())),
                    str(e.get("msg", "")).removeprefix("Value error, "),
                    str(e.get("type", "value_error")),
                )
                for e in exc.errors()
            ]
        )

    @app.exception_handler(RequestFieldError)
    async def _refused(request: Request, exc: RequestFieldError) -> JSONResponse:
        return validation_response([(loc, msg, "value_error") for loc, msg in exc.errors])

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        if exc.status_code == 422:
            return validation_response([((), str(exc.detail), "value_error")])
        headers = dict(exc.headers or {})
        if exc.status_code == 405:
            headers["Allow"] = _allowed_methods(request)
        return JSONResponse(status_code=exc.status_code, content={"detail": str(exc.detail)}, headers=headers)

    @app.exception_handler(NotFound)
    async def _not_found(request: Request, exc: NotFound) -> JSONResponse:
        return JSONResponse(status_code=404, content={"detail": str(exc)})

    @app.exception_handler(StoreError)
    async def _conflict(request: Request, exc: StoreError) -> JSONResponse:
        return JSONResponse(status_code=409, content={"detail": str(exc)})

    @app.exception_handler(QueueFull)
    async def _queue_full(request: Request, exc: QueueFull) -> JSONResponse:
        return JSONResponse(
            status_code=429, content={"detail": str(exc)}, headers={"Retry-After": str(exc.retry_after_s)}
        )

    @app.exception_handler(ServiceError)
    async def _bad(request: Request, exc: ServiceError) -> JSONResponse:
        return JSONResponse(status_code=400, content={"detail": str(exc)})
