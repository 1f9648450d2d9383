"""Errors of the SICK CoLa codec (LMS100 / LMS1xx family)."""

from __future__ import annotations

from drivers.errors import DriverError

# sFA error codes as the SOPAS telegram listing names them (section 4 of shared/reference/sick-cola.md).
SFA_ERRORS: dict[int, tuple[str, str]] = {
    0x00: ("Sopas_Ok", "no error"),
    0x01: ("METHODIN_ACCESSDENIED", "wrong user level (access denied) for this method"),
    0x02: ("METHODIN_UNKNOWNINDEX", "unknown method"),
    0x03: ("VARIABLE_UNKNOWNINDEX", "unknown variable"),
    0x04: ("LOCALCONDITIONFAILED", "value out of the allowed range (local condition failed)"),
    0x05: ("INVALID_DATA", "invalid data"),
    0x06: ("UNKNOWN_ERROR", "error of unknown cause"),
    0x07: ("BUFFER_OVERFLOW", "reply would not fit (buffer overflow)"),
    0x08: ("BUFFER_UNDERFLOW", "request too short or parameters missing (buffer underflow)"),
    0x09: ("ERROR_UNKNOWN_TYPE", "variable of unknown type"),
    0x0A: ("VARIABLE_WRITE_ACCESSDENIED", "variable is read-only or the access level is too low"),
    0x0B: ("UNKNOWN_CMD_FOR_NAMESERVER", "name not known to the name server"),
    0x0C: ("UNKNOWN_COLA_COMMAND", "command type is not a CoLa command"),
    0x0D: ("METHODIN_SERVER_BUSY", "another method is still running (server busy)"),
    0x0E: ("FLEX_OUT_OF_BOUNDS", "array length out of bounds"),
    0x0F: ("EVENTREG_UNKNOWNINDEX", "unknown event"),
    0x10: ("COLA_A_VALUE_OVERFLOW", "number too large for the field (CoLa A value overflow)"),
    0x11: ("COLA_A_INVALID_CHARACTER", "invalid character in a CoLa A telegram"),
    0x12: ("OSAI_NO_MESSAGE", "internal error: no message (on read)"),
    0x13: ("OSAI_NO_ANSWER_MESSAGE", "internal error: no answer message (on write)"),
    0x14: ("INTERNAL", "internal firmware error"),
    0x15: ("HubAddressCorrupted", "SOPAS hub address corrupted"),
    0x16: ("HubAddressDecoding", "SOPAS hub address decoding error"),
    0x17: ("HubAddressAddressExceeded", "SOPAS hub address exceeded"),
    0x18: ("HubAddressBlankExpected", "SOPAS hub address: blank expected"),
    0x19: ("AsyncMethodsAreSuppressed", "asynchronous methods are suppressed"),
    0x20: ("ComplexArraysNotSupported", "complex arrays not supported"),
}


def sfa_message(code: int) -> str:
    """Human-readable text for an ``sFA`` error code (unknown codes are said to be unknown)."""
    entry = SFA_ERRORS.get(code)
    if entry is None:
        return f"sFA error 0x{code:02X}: code not in the SOPAS error table"
    name, text = entry
    return f"sFA error 0x{code:02X} {name}: {text}"


class CoLaError(DriverError):
    """Base class of every error raised by the CoLa codec."""


class FramingError(CoLaError):
    """A frame was broken: bad checksum, absurd length, or malformed start/end."""


class TelegramError(CoLaError):
    """The frame was fine but its contents could not be parsed or encoded (unknown command, bad field)."""


class DeviceErrorReply(CoLaError):
    """The device answered ``sFA <code>``."""

    def __init__(self, code: int, request: str | None = None) -> None:
        self.code = code
        self.message = sfa_message(code)
        self.request = request
        super().__init__(self.message if request is None else f"{request}: {self.message}")
