"""Helpers shared by the servo tests."""

from __future__ import annotations

import time


def wait_for(predicate: object, timeout: float = 10.0) -> None:
    """Wait for a condition driven by other threads (a deadline against hangs, not a timing check)."""
    assert callable(predicate)
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met in time")
        time.sleep(0.005)
