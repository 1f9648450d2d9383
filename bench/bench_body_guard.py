"""Benchmark of the body guard (printed, never asserted): what a 40 MiB POST costs the API.

Refused: an unauthenticated 40 MiB JSON POST, answered 401 by the body guard from its headers.
Baseline in the same run: the same 40 MiB POST with the operator token and a body limit raised to
64 MiB, so FastAPI reads and parses all of it (then 422 for the unknown field): what every
unauthenticated POST cost before the guard. For each, the time to the answer as the uploading
client sees it, and the longest ``/healthz`` round trip of a prober polling every 5 ms meanwhile
(the server's stall). A third row, idle: the prober alone for 0.5 s (the machine's own noise).
Server, uploader and prober are three processes.

Run: ``.venv/bin/python -m bench.bench_body_guard [--mib 40] [--runs 3]``
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import tempfile
import time
from pathlib import Path
from typing import Any

TOKEN = "bench-operator"


def _upload(url: str, mib: int, token: str | None, out: Any) -> None:
    import httpx

    payload = b'{"target": "cylinder", "pad": "' + b"x" * (mib << 20) + b'"}'
    headers = {"Content-Type": "application/json"}
    if token is not None:
        headers["Authorization"] = f"Bearer {token}"
    t0 = time.perf_counter()
    r = httpx.post(f"{url}/api/v1/measurements", content=payload, headers=headers, timeout=120)
    out.put((r.status_code, time.perf_counter() - t0))


def _probe(url: str, stop: Any, out: Any) -> None:
    import httpx

    worst = 0.0
    with httpx.Client(base_url=url) as client:
        while not stop.is_set():
            t0 = time.perf_counter()
            client.get("/healthz")
            worst = max(worst, time.perf_counter() - t0)
            time.sleep(0.005)
    out.put(worst)


def one(url: str, mib: int, token: str | None, upload: bool = True) -> tuple[int, float, float]:
    """(status, seconds to the answer, worst /healthz round trip meanwhile in seconds); without
    ``upload`` the prober alone for 0.5 s (status 0)."""
    ctx = mp.get_context("spawn")
    stop, results, worst = ctx.Event(), ctx.Queue(), ctx.Queue()
    prober = ctx.Process(target=_probe, args=(url, stop, worst))
    prober.start()
    time.sleep(1.0)  # the prober's imports
    if upload:
        uploader = ctx.Process(target=_upload, args=(url, mib, token, results))
        uploader.start()
        status, dt = results.get(timeout=300)
        uploader.join()
    else:
        time.sleep(0.5)
        status, dt = 0, 0.5
    time.sleep(0.2)
    stop.set()
    w = worst.get(timeout=30)
    prober.join()
    return status, dt, w


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mib", type=int, default=40)
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()

    from service.api import ServerThread, Service, create_app
    from service.config import parse_toml

    with tempfile.TemporaryDirectory() as tmp:
        cfg = parse_toml(
            f"[sim]\n[storage]\ndir = '{Path(tmp)}'\n[auth]\nread = 'open'\noperator_token = '{TOKEN}'\n"
            f"[api]\nmax_body_bytes = {64 << 20}\n"
        )
        svc = Service(cfg, lambda ctx: {})
        with ServerThread(create_app(svc, manage_lifecycle=False)) as srv:
            rows: dict[str, list[tuple[int, float, float]]] = {"refused": [], "parsed": [], "idle": []}
            for _ in range(args.runs):
                rows["refused"].append(one(srv.url, args.mib, None))
                rows["parsed"].append(one(srv.url, args.mib, TOKEN))
                rows["idle"].append(one(srv.url, args.mib, None, upload=False))
    for name, runs in rows.items():
        for status, dt, w in runs:
            what = "no upload, 0.5 s" if name == "idle" else f"{args.mib} MiB POST: {status} after {dt:.3f} s"
            print(f"{name:8s} {what}; /healthz worst {w * 1e3:.1f} ms")
    med = {k: sorted(v, key=lambda r: r[2])[len(v) // 2] for k, v in rows.items()}
    print(
        f"median worst /healthz: idle {med['idle'][2] * 1e3:.1f} ms, refused {med['refused'][2] * 1e3:.1f} ms, "
        f"parsed (baseline) "
        f"{med['parsed'][2] * 1e3:.1f} ms: {med['parsed'][2] / max(med['refused'][2], 1e-9):.1f}x less stall"
    )


if __name__ == "__main__":
    main()
