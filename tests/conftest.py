"""Shared pytest fixtures."""

from __future__ import annotations

import signal
from pathlib import Path

from hypothesis import HealthCheck, settings

import service.simdevices  # noqa: F401  (registers the sim:// device URLs, as the CLI and service do)

# No per-example deadline (200 ms by default) and no "too slow" health check: both time the machine, and a
# stall on a loaded CI machine fails them with no bug. The properties stay as they are; pytest-timeout
# catches hangs. A test's own @settings still chooses its example count.
settings.register_profile("lrms", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("lrms")

# Started as a background job of a script (``.ci/run &``, ``cmd & wait``), this process inherits SIGINT
# ignored, and so would every ``lrms sim ...`` child a test stops with SIGINT: it would never stop. Let
# SIGINT interrupt again (children then start with the default disposition, as from a terminal).
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

REPO = Path(__file__).resolve().parent.parent
"""The repository root. Tests read only what is inside it (recorded data: ``tests/data/``)."""
