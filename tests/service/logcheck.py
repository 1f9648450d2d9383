"""Checks of raw logs shared by the service tests."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from service import mcaplog

JS_MAX_SAFE = 2**53 - 1
"""The largest integer a JavaScript number (Foxglove's JSON reader) holds exactly."""


def big_integers(value: Any, path: str = "") -> Iterator[tuple[str, int]]:
    """Every integer of a decoded JSON value that a JavaScript number cannot hold exactly."""
    if isinstance(value, dict):
        for k, v in value.items():
            yield from big_integers(v, f"{path}.{k}")
    elif isinstance(value, list):
        for i, v in enumerate(value):
            yield from big_integers(v, f"{path}[{i}]")
    elif isinstance(value, int) and not isinstance(value, bool) and abs(value) > JS_MAX_SAFE:
        yield path, value


def assert_json_is_javascript_safe(msgs: list[mcaplog.LoggedMessage]) -> None:
    """No integer above 2^53 anywhere in the log's JSON messages, and the sweep's instants are
    Foxglove ``{sec, nsec}`` times that agree with their messages' log times."""
    json_msgs = [m for m in msgs if m.encoding == "json"]
    assert json_msgs
    bad = [(m.topic + p, v) for m in json_msgs for p, v in big_integers(m.decode())]
    assert not bad, bad[:10]
    for m in json_msgs:
        ev = m.decode()
        if m.topic == mcaplog.TOPIC_EVENT and ev["kind"] in ("sweep_start", "sweep_end"):
            assert set(ev["time"]) == {"sec", "nsec"} and 0 <= ev["time"]["nsec"] < 10**9, ev
            assert abs(mcaplog.time_ns_of(ev["time"]) - m.log_time_ns) < 10**9  # the same instant, roughly
