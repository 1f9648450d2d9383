"""Exception hierarchy shared by every driver."""

from __future__ import annotations


class DriverError(Exception):
    """Base class of every error a driver raises on purpose."""


class DeviceURLError(DriverError, ValueError):
    """A device URL could not be parsed, names an unknown scheme, or carries bad options."""


class DeviceTimeoutError(DriverError, TimeoutError):
    """A device did not answer within the request timeout."""


class DeviceConnectionError(DriverError, ConnectionError):
    """The link to a device could not be opened or was lost."""
