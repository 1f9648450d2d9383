"""Exceptions of the service layer."""

from __future__ import annotations


class ServiceError(Exception):
    """Base class of errors raised on purpose by the service (bad config, bad request, ...)."""


class ConfigError(ServiceError, ValueError):
    """The rig configuration is invalid."""
