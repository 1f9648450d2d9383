"""``lrms measure --server URL``: the measurement on a running ``lrms serve``, over its REST API.

The rig, the sweep and the fit are the service's; this process only posts the request
(``POST /api/v1/measurements``), follows it (``GET /api/v1/measurements/ID`` every 0.1 s, the
progress bar on stderr), fetches the raw log and the cloud when ``--out`` / ``--cloud`` ask for
them, and prints the fit's result as JSON. It imports the standard library only (``urllib``, no
numpy, pydantic or HTTP client library): its start is the interpreter's, not the rig's
(bench/bench_cli_start.py). The request is checked by the service (a refusal is its 422 message);
Ctrl-C cancels the measurement on the service before the command ends: from the request on (a
Ctrl-C while the request is on its way is held until the service answers with the measurement's
id, a second one ends the command at once); ``--wait SECONDS`` bounds the whole wait the same way.
The HTTP client is :mod:`service.cli._http` (shared with ``lrms report``).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from service.cli._http import ApiClient, token_from
from service.errors import ServiceError

#: Environment variables tried for the bearer token when ``--token`` is not given, in this order
#: (a measurement needs the operator or admin token; ``LRMS_API_TOKEN`` is the operator token's old name).
TOKEN_VARS = ("LRMS_OPERATOR_TOKEN", "LRMS_ADMIN_TOKEN", "LRMS_API_TOKEN")
#: Seconds between two reads of the measurement's state.
POLL_S = 0.1
#: Seconds to wait for each answer of the service when ``--timeout`` is not given.
DEFAULT_TIMEOUT_S = 30.0
#: Options of the embedded rig that a running service does not take from its client.
LOCAL_ONLY = (("config", "--config"), ("data", "--data"), ("plot", "--plot"))
#: Options that only the client of a running service takes.
REMOTE_ONLY = (("token", "--token"), ("timeout", "--timeout"), ("wait", "--wait"))
FINAL = ("done", "failed", "cancelled")


class _Held:
    """Whether a Ctrl-C came while it was held."""

    interrupted = False


@contextmanager
def _hold_ctrl_c() -> Iterator[_Held]:
    """Hold the first Ctrl-C (SIGINT) inside the block: it is noted, not raised, so the request in
    flight gets its answer (the measurement's id, to cancel it by); a second one raises at once."""
    held = _Held()
    if threading.current_thread() is not threading.main_thread():
        yield held
        return

    def on_sigint(signum: int, frame: object) -> None:
        if held.interrupted:
            raise KeyboardInterrupt
        held.interrupted = True
        print("\ninterrupted: cancelling once the service answers (Ctrl-C again to leave now)", file=sys.stderr)

    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        yield held
    finally:
        signal.signal(signal.SIGINT, previous)


def _checked(m: dict[str, Any], client: ApiClient, path: str) -> dict[str, Any]:
    if not isinstance(m.get("id"), str | int) or m.get("state") not in (*FINAL, "queued", "running"):
        raise ServiceError(f"the reply to {path} from {client.base} is not an lrms API answer (no measurement)")
    return m


def _cancel(client: ApiClient, path: str, mid: str) -> None:
    """Cancel the measurement on the service (best effort: a failure is reported, not raised)."""
    try:
        client.json("POST", f"{path}/cancel")
    except ServiceError as exc:
        print(f"\ncould not cancel measurement {mid}: {exc}", file=sys.stderr)


def run_remote(args: argparse.Namespace) -> int:
    from service.cli.measure import progress_bar, request_body

    given = [flag for attr, flag in LOCAL_ONLY if getattr(args, attr, None) is not None]
    if given:
        raise ServiceError(f"not with --server: {', '.join(given)} (the service has its own rig, storage and plots)")
    if args.wait is not None and not args.wait > 0:
        raise ServiceError(f"--wait must be positive, got {args.wait}")
    timeout = DEFAULT_TIMEOUT_S if args.timeout is None else args.timeout
    client = ApiClient(args.server, token_from(args.token, TOKEN_VARS), timeout)
    deadline = None if args.wait is None else time.monotonic() + args.wait
    try:
        with _hold_ctrl_c() as held:
            m = _checked(
                client.json("POST", "/api/v1/measurements", request_body(args)), client, "POST /api/v1/measurements"
            )
    except KeyboardInterrupt:
        print("\nthe measurement may be queued on the service (its id was not answered yet)", file=sys.stderr)
        raise
    mid = str(m["id"])
    path = f"/api/v1/measurements/{mid}"
    try:
        if held.interrupted:
            raise KeyboardInterrupt
        while m["state"] not in FINAL:
            if deadline is not None and time.monotonic() >= deadline:
                _cancel(client, path, mid)
                raise ServiceError(
                    f"measurement {mid} did not end within --wait {args.wait:g} s (it was {m['state']}); "
                    "cancelled on the service"
                )
            if not args.quiet:
                bar = progress_bar(float(m.get("progress") or 0.0), str(m.get("message") or m["state"]))
                print(bar, end="", file=sys.stderr, flush=True)
            time.sleep(POLL_S if deadline is None else max(0.0, min(POLL_S, deadline - time.monotonic())))
            m = _checked(client.json("GET", path), client, f"GET {path}")
    except KeyboardInterrupt:
        if m["state"] not in FINAL:
            _cancel(client, path, mid)  # leave no orphan sweep on the rig
        raise
    if not args.quiet:
        print(file=sys.stderr)
    if m.get("has_raw") and args.out:
        client.download(f"{path}/raw", args.out)
    if m.get("has_cloud") and args.cloud:
        client.download(f"{path}/cloud", args.cloud)
    if m["state"] != "done" or not isinstance(m.get("result"), dict):
        raise ServiceError(f"measurement {mid} {m['state']}: {m.get('error')} (raw log: {client.base}{path}/raw)")
    result = dict(m["result"])
    result.setdefault("measurement_id", mid)  # the service's result names it too
    result["raw_url"] = f"{client.base}{path}/raw" if m.get("has_raw") else None
    result["cloud_url"] = f"{client.base}{path}/cloud" if m.get("has_cloud") else None
    print(json.dumps(result, indent=2))
    return 0
