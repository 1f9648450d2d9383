"""Device URLs, in the manner of pyserial's ``serial_for_url`` and python-can's interface names.

Examples::

    tcp://10.0.0.5:2112?cola=b          # SICK scanner over TCP, CoLa B
    sim://?scene=seed003                # simulated scanner (handler in service.simdevices)
    canopen+socketcan://can0?node=1     # CiA 402 drive over python-can
    modbus-rtu:///dev/ttyUSB0?baud=115200&unit=1

A URL is parsed once into a :class:`DeviceURL`. Handlers read their options through the typed
getters, which record what was used; :meth:`DeviceURL.check_all_used` then rejects any option
nobody asked for, so that a typo (``?cloa=b``) is an error instead of a silent default.

Handlers are looked up by device *kind* ("scanner", "motor") and scheme. A scheme of the form
``family+sub`` (``canopen+socketcand``) is first looked up whole, then by ``family+``.
Handlers are registered either directly (:func:`register`) or lazily by dotted path, so that
this module does not import the packages that provide them.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import parse_qsl, unquote, urlsplit

from drivers.errors import DeviceURLError

_TRUE = {"1", "true", "yes", "on"}
_FALSE = {"0", "false", "no", "off"}


@dataclass
class DeviceURL:
    """A parsed device URL with typed, use-tracked option getters."""

    raw: str
    scheme: str
    host: str | None
    port: int | None
    path: str
    query: dict[str, str]
    _used: set[str] = field(default_factory=set, repr=False, compare=False)

    @classmethod
    def parse(cls, url: str) -> DeviceURL:
        if not isinstance(url, str) or "://" not in url:
            raise DeviceURLError(f"not a device URL (expected scheme://...): {url!r}")
        parts = urlsplit(url)
        if not parts.scheme:
            raise DeviceURLError(f"device URL has no scheme: {url!r}")
        try:
            port = parts.port
        except ValueError as exc:
            raise DeviceURLError(f"bad port in device URL {url!r}: {exc}") from None
        query: dict[str, str] = {}
        for key, value in parse_qsl(parts.query, keep_blank_values=True, strict_parsing=False):
            if key in query:
                raise DeviceURLError(f"option {key!r} given twice in {url!r}")
            query[key] = value
        return cls(
            raw=url,
            scheme=parts.scheme.lower(),
            host=parts.hostname,
            port=port,
            path=unquote(parts.path),
            query=query,
        )

    # -- typed option getters -------------------------------------------------------------
    def has(self, name: str) -> bool:
        return name in self.query

    def get_str(self, name: str, default: str | None = None, choices: tuple[str, ...] | None = None) -> str:
        self._used.add(name)
        value = self.query.get(name, default)
        if value is None:
            raise DeviceURLError(f"option {name!r} is required in {self.raw!r}")
        if choices is not None and value not in choices:
            raise DeviceURLError(f"option {name}={value!r} in {self.raw!r}: expected one of {', '.join(choices)}")
        return value

    def get_int(self, name: str, default: int | None = None, lo: int | None = None, hi: int | None = None) -> int:
        self._used.add(name)
        if name not in self.query:
            if default is None:
                raise DeviceURLError(f"option {name!r} is required in {self.raw!r}")
            return default
        text = self.query[name]
        try:
            value = int(text, 0)
        except ValueError:
            raise DeviceURLError(f"option {name}={text!r} in {self.raw!r} is not an integer") from None
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise DeviceURLError(f"option {name}={value} in {self.raw!r} is outside [{lo}, {hi}]")
        return value

    def get_float(
        self, name: str, default: float | None = None, lo: float | None = None, hi: float | None = None
    ) -> float:
        self._used.add(name)
        if name not in self.query:
            if default is None:
                raise DeviceURLError(f"option {name!r} is required in {self.raw!r}")
            return default
        text = self.query[name]
        try:
            value = float(text)
        except ValueError:
            raise DeviceURLError(f"option {name}={text!r} in {self.raw!r} is not a number") from None
        if value != value or (lo is not None and value < lo) or (hi is not None and value > hi):
            raise DeviceURLError(f"option {name}={value} in {self.raw!r} is outside [{lo}, {hi}]")
        return value

    def get_bool(self, name: str, default: bool = False) -> bool:
        self._used.add(name)
        if name not in self.query:
            return default
        text = self.query[name].lower()
        if text in _TRUE or text == "":
            return True
        if text in _FALSE:
            return False
        raise DeviceURLError(f"option {name}={self.query[name]!r} in {self.raw!r} is not a boolean")

    def check_all_used(self) -> None:
        """Raise :class:`DeviceURLError` if the URL carries options no handler read."""
        unknown = sorted(set(self.query) - self._used)
        if unknown:
            known = ", ".join(sorted(self._used)) or "none"
            raise DeviceURLError(f"unknown option(s) {', '.join(unknown)} in {self.raw!r} (this device takes: {known})")


Handler = Callable[..., Any]
_registry: dict[tuple[str, str], Handler | str] = {}


def register(kind: str, scheme: str, handler: Handler | str) -> None:
    """Register ``handler`` for URLs of ``scheme`` opening a device of ``kind``.

    ``handler`` is a callable ``handler(url: DeviceURL, **kwargs)`` or a ``"module:function"``
    string imported on first use. ``scheme`` may end in ``+`` to cover a family (``canopen+``).
    """
    _registry[(kind, scheme.lower())] = handler


def registered_schemes(kind: str) -> list[str]:
    return sorted(s for (k, s) in _registry if k == kind)


def _resolve(kind: str, scheme: str) -> Handler:
    entry = _registry.get((kind, scheme))
    if entry is None and "+" in scheme:
        entry = _registry.get((kind, scheme.split("+", 1)[0] + "+"))
    if entry is None:
        known = ", ".join(registered_schemes(kind)) or "none"
        raise DeviceURLError(f"no {kind} driver for scheme {scheme!r} (known: {known})")
    if isinstance(entry, str):
        module_name, _, attr = entry.partition(":")
        module = importlib.import_module(module_name)
        entry = getattr(module, attr)
        _registry[(kind, scheme)] = entry
    return entry


def open_device(kind: str, url: str | DeviceURL, **kwargs: Any) -> Any:
    """Open a device of ``kind`` from its URL; extra keyword arguments go to the handler."""
    parsed = url if isinstance(url, DeviceURL) else DeviceURL.parse(url)
    handler = _resolve(kind, parsed.scheme)
    return handler(parsed, **kwargs)


# Built-in handlers, imported on first use. The ``sim://`` schemes join the simulator and the
# drivers, so the composition root registers them (``import service.simdevices``).
register("scanner", "tcp", "drivers.lms100.client:open_url")
register("motor", "canopen+", "drivers.servo.cia402_can:open_url")
register("motor", "modbus-rtu", "drivers.servo.modbus_backend:open_url")
register("motor", "modbus-rtu+", "drivers.servo.modbus_backend:open_url")
