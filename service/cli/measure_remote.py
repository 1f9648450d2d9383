"""``lrms measure --server URL``: the measurement on a running ``lrms serve``, over its REST API.

The rig, the sweep and the fit are the service's; this process only posts the request
(``POST /api/v1/measurements``), follows it (``GET /api/v1/measurements/ID`` every 0.1 s, the
progress bar on stderr), fetches the raw log and the cloud when ``--out`` / ``--cloud`` ask for
them, and prints the fit's result as JSON. It imports the standard library only (``urllib``, no
numpy, pydantic or HTTP client library): its start is the interpreter's, not the rig's
(bench/bench_cli_start.py). The request is checked by the service (a refusal is its 422 message);
Ctrl-C cancels the measurement on the service before the command ends.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
import urllib.error
import urllib.request
from typing import Any

from service.errors import ServiceError

#: Environment variables tried for the bearer token when ``--token`` is not given, in this order
#: (a measurement needs the operator or admin token; ``LRMS_API_TOKEN`` is the operator token's old name).
TOKEN_VARS = ("LRMS_OPERATOR_TOKEN", "LRMS_ADMIN_TOKEN", "LRMS_API_TOKEN")
#: Seconds between two reads of the measurement's state.
POLL_S = 0.1
#: Options of the embedded rig that a running service does not take from its client.
LOCAL_ONLY = (("config", "--config"), ("data", "--data"), ("plot", "--plot"))


class _Client:
    def __init__(self, base: str, token: str | None, timeout: float) -> None:
        self.base = base.rstrip("/")
        self.headers = {"Accept": "application/json"}
        if token:
            self.headers["Authorization"] = f"Bearer {token}"
        self.timeout = timeout

    def open(self, method: str, path: str, body: dict[str, Any] | None = None) -> Any:
        """The response of ``method path`` (a file-like object); HTTP errors as :class:`ServiceError`."""
        headers = dict(self.headers)
        data = None
        if body is not None:
            data = json.dumps(body).encode()
            headers["Content-Type"] = "application/json"
        req = urllib.request.Request(self.base + path, data=data, headers=headers, method=method)
        try:
            return urllib.request.urlopen(req, timeout=self.timeout)
        except urllib.error.HTTPError as exc:
            raise ServiceError(f"the service answered {exc.code} to {method} {path}: {_detail(exc)}") from None
        except (urllib.error.URLError, OSError) as exc:
            reason = getattr(exc, "reason", exc)
            raise ServiceError(f"cannot reach the service at {self.base}: {reason}") from None

    def json(self, method: str, path: str, body: dict[str, Any] | None = None) -> dict[str, Any]:
        with self.open(method, path, body) as r:
            out: dict[str, Any] = json.load(r)
        return out

    def download(self, path: str, dest: str) -> None:
        with self.open("GET", path) as r, open(dest, "wb") as f:
            shutil.copyfileobj(r, f)


def _detail(exc: urllib.error.HTTPError) -> str:
    """The error body's message: ``message`` (a 422's summary), else ``detail``, else the text."""
    try:
        raw = exc.read()
    except OSError:
        return str(exc.reason)
    try:
        body = json.loads(raw)
    except ValueError:
        return raw.decode(errors="replace")[:200] or str(exc.reason)
    if isinstance(body, dict):
        return str(body.get("message") or body.get("detail") or body)
    return str(body)


def run_remote(args: argparse.Namespace) -> int:
    from service.cli.measure import _bar, request_body

    given = [flag for attr, flag in LOCAL_ONLY if getattr(args, attr, None) is not None]
    if given:
        raise ServiceError(f"not with --server: {', '.join(given)} (the service has its own rig, storage and plots)")
    if args.timeout <= 0:
        raise ServiceError(f"--timeout must be positive, got {args.timeout}")
    token = args.token or next((os.environ[v] for v in TOKEN_VARS if os.environ.get(v)), None)
    client = _Client(args.server, token, args.timeout)
    m = client.json("POST", "/api/v1/measurements", request_body(args))
    mid = str(m["id"])
    path = f"/api/v1/measurements/{mid}"
    try:
        while m["state"] not in ("done", "failed", "cancelled"):
            if not args.quiet:
                bar = _bar(float(m.get("progress") or 0.0), str(m.get("message") or m["state"]))
                print(bar, end="", file=sys.stderr, flush=True)
            time.sleep(POLL_S)
            m = client.json("GET", path)
    except KeyboardInterrupt:
        try:  # leave no orphan sweep on the rig
            client.json("POST", f"{path}/cancel")
        except ServiceError as exc:
            print(f"\ncould not cancel measurement {mid}: {exc}", file=sys.stderr)
        raise
    if not args.quiet:
        print(file=sys.stderr)
    if m["has_raw"] and args.out:
        client.download(f"{path}/raw", args.out)
    if m["has_cloud"] and args.cloud:
        client.download(f"{path}/cloud", args.cloud)
    if m["state"] != "done" or m["result"] is None:
        raise ServiceError(f"measurement {mid} {m['state']}: {m['error']} (raw log: {client.base}{path}/raw)")
    result = dict(m["result"])
    result.setdefault("measurement_id", mid)  # the service's result names it too
    result["raw_url"] = f"{client.base}{path}/raw" if m["has_raw"] else None
    result["cloud_url"] = f"{client.base}{path}/cloud" if m["has_cloud"] else None
    print(json.dumps(result, indent=2))
    return 0
