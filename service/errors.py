"""Exceptions of the service layer."""

from __future__ import annotations

from collections.abc import Sequence


class ServiceError(Exception):
    """Base class of errors raised on purpose by the service (bad config, bad request, ...)."""


class ConfigError(ServiceError, ValueError):
    """The rig configuration is invalid."""


Loc = tuple[str | int, ...]


class RequestFieldError(ServiceError, ValueError):
    """A request is refused because of named fields (the REST API answers 422 with them).

    Raised where a check needs more than the request's own schema: the rig's travel limits and
    maximum speed, the planned duration, a schedule's minimum interval. ``errors`` holds
    ``(loc, message)`` pairs, ``loc`` relative to the model that was checked (``("sweep",
    "speed_deg_s")``); :meth:`under` puts them below a parent (``("body",)``).
    """

    def __init__(self, errors: Sequence[tuple[Loc, str]]) -> None:
        if not errors:
            raise ValueError("RequestFieldError needs at least one error")
        self.errors: list[tuple[Loc, str]] = [(tuple(loc), msg) for loc, msg in errors]
        super().__init__("; ".join(f"{'.'.join(str(x) for x in loc)}: {msg}" for loc, msg in self.errors))

    def under(self, *prefix: str | int) -> RequestFieldError:
        """The same errors with ``prefix`` in front of every location."""
        return RequestFieldError([((*prefix, *loc), msg) for loc, msg in self.errors])
