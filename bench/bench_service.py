"""Benchmarks of the acquisition service (printed, never asserted).

1. Ingest pipeline: CoLa B LMDscandata telegrams (1081 beams, ray-cast by the simulated LMS100)
   -> decode -> record (clock model, gap count) -> raw log (telegram, LaserScan, /tf to MCAP on
   its thread) -> map to 3D, as scans per second and as a multiple of the sensor's 25 scans/s.
   The decode-only rate of the same telegrams is printed as the baseline of this run. One short
   warm-up run, then five runs; the median is the figure (each run is printed too).
2. REST under load: the service (``lrms serve`` on the default simulated rig, its own process)
   runs a slow sweep while N concurrent clients, spread over a few load processes (``--processes``,
   none of them the server's), poll it for D seconds; errors, p50/p99 latency as the client sees
   it, the time spent in the app (``Server-Timing``), how late the API's event loop and the load
   processes' loops woke (stalls of either process), and scans dropped (scan-counter gaps and
   client queue drops) of that sweep. Baselines in the same run: the same requests from one
   client with the rig idle, and the same N clients with the rig idle (10 s).

Run: ``.venv/bin/python -m bench.bench_service [--clients 100] [--duration 30] [--scans 500] [--processes 4]``
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import os
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent


def _telegrams(n: int) -> list[bytes]:
    from drivers.lms100.messages import ScanDataEvent
    from drivers.lms100.protocol import CoLaConnection
    from sim.scanner.device import SimulatedLMS100

    dev = SimulatedLMS100("seed003", realtime=False, motor_angle_at=lambda t: 0.3 + 0.17 * np.asarray(t))
    conn = CoLaConnection("b", role="device")
    return [conn.send(ScanDataEvent(dev.stamp(dev.make_scan(k)))) for k in range(n)]


def _pipeline(frames: list[bytes], path: Path) -> tuple[float, int, int]:
    """decode -> record -> raw log -> map for ``frames``; wall time (log closed), MCAP bytes, points."""
    from drivers.lms100.messages import ScanDataEvent
    from drivers.lms100.protocol import CoLaConnection
    from lrms.kinematics import RigCalibration
    from service.mcaplog import McapLog
    from service.sweep import SweepRecorder

    t0 = time.perf_counter()
    conn = CoLaConnection("b", role="client")
    log = McapLog(path)
    rec = SweepRecorder(RigCalibration(), log, "b")
    host0 = 1_763_700_000_000_000_000
    for k, f in enumerate(frames):
        t_ns = host0 + k * 40_000_000
        rec.add_motor(t_ns - 5_000_000, 0.3 + 0.17 * k * 0.04, 0.17)
        rec.add_motor(t_ns + 5_000_000, 0.3 + 0.17 * (k * 0.04 + 0.01), 0.17)
        conn.receive_data(f)
        msg = conn.next_message()
        assert isinstance(msg, ScanDataEvent)
        rec.add_scan(msg.scan, t_ns, f)
    mapped = rec.map(0, None, None, 0.05, 20.0)
    log.log_cloud(host0, mapped.points)
    log.close()
    return time.perf_counter() - t0, path.stat().st_size, int(mapped.points.shape[0])


def bench_ingest(n_scans: int, repeats: int = 5) -> dict[str, Any]:
    from drivers.lms100.protocol import CoLaConnection

    frames = _telegrams(n_scans)
    # baseline: decode only
    t0 = time.perf_counter()
    conn = CoLaConnection("b", role="client")
    for f in frames:
        conn.receive_data(f)
        conn.next_message()
    decode_s = time.perf_counter() - t0
    # the pipeline: one warm-up run (first-call costs: schema registration, numpy and protobuf
    # warm-up, a cold page cache), then ``repeats`` runs; the median is the figure
    with tempfile.TemporaryDirectory() as tmp:
        _pipeline(frames[: min(100, n_scans)], Path(tmp) / "warm.mcap")
        runs = [_pipeline(frames, Path(tmp) / f"bench{i}.mcap") for i in range(repeats)]
    walls = sorted(r[0] for r in runs)
    return {
        "scans": n_scans,
        "decode_scans_per_s": n_scans / decode_s,
        "pipeline_scans_per_s": n_scans / float(np.median(walls)),
        "pipeline_runs_scans_per_s": [n_scans / w for w in walls[::-1]],
        "mcap_bytes_per_scan": runs[0][1] / n_scans,
        "points": float(runs[0][2]),
    }


def _server_ms(r: Any) -> float:
    """The app's own time of a response (``Server-Timing: app;dur=<ms>``), NaN without one."""
    for part in r.headers.get("server-timing", "").split(","):
        name, _, dur = part.strip().partition(";dur=")
        if name == "app" and dur:
            return float(dur)
    return float("nan")


async def _load(
    base: str,
    paths: list[str],
    clients: int,
    duration: float,
    interval: float = 0.0,
    server: list[float] | None = None,
    wait_go: bool = False,
    client_lag: list[float] | None = None,
    by_path: dict[str, list[float]] | None = None,
    starts: list[float] | None = None,
) -> tuple[list[float], int, int, float]:
    """``clients`` concurrent clients for ``duration`` s; returns latencies, errors, requests and the
    time the clients took to open their connections (warm-up, not counted in the latencies).
    ``server`` (if given) receives the app's own time of each response (ms). With ``wait_go``
    (a load process), print ``ready`` once imported and wait for ``go`` on stdin, so that no load
    process is still starting up (importing, a CPU burst) while the others measure. ``client_lag``
    (if given) receives how late (ms) this process's own event loop woke from 20 ms sleeps during
    the load: time a response may have waited in the client, not in the server."""
    import httpx

    start_at = 0.0  # wall-clock time at which all load processes start measuring
    if wait_go:
        print("ready", flush=True)
        go, _, when = (await asyncio.to_thread(sys.stdin.readline)).strip().partition(" ")
        if go != "go":
            raise RuntimeError("load worker: expected 'go <start time>' on stdin")
        start_at = float(when or 0.0)
        # the load generator's own garbage collections are not the server's latency
        gc.collect()
        gc.freeze()
        gc.disable()

    latencies: list[float] = []
    errors = 0
    requests = 0
    limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)
    async with httpx.AsyncClient(base_url=base, timeout=10.0, limits=limits) as client:
        t_warm = time.perf_counter()  # an HMI opens its connection once and keeps it
        warm = await asyncio.gather(*(client.get(paths[0]) for _ in range(clients)), return_exceptions=True)
        warmup_s = time.perf_counter() - t_warm
        errors += sum(1 for r in warm if isinstance(r, BaseException))
        # every process opens its connections first (a burst of connects and requests), then
        # all measure from the same instant
        await asyncio.sleep(max(0.0, start_at - time.time()))
        end = time.monotonic() + duration

        async def worker(i: int) -> None:
            nonlocal errors, requests
            j = i
            if interval > 0:  # HMIs are not synchronised: first polls spread over one interval
                await asyncio.sleep(interval * random.random())
            while time.monotonic() < end:
                path = paths[j % len(paths)]
                j += 1
                t = time.perf_counter()
                try:
                    r = await client.get(path)
                    ok = r.status_code == 200
                    if server is not None:
                        server.append(_server_ms(r))
                except httpx.HTTPError:
                    ok = False
                latencies.append(time.perf_counter() - t)
                if starts is not None:
                    starts.append(time.time() - latencies[-1])
                if by_path is not None:
                    by_path.setdefault(path, []).append(latencies[-1])
                requests += 1
                if not ok:
                    errors += 1
                if interval > 0:  # an HMI polls, it does not hammer
                    await asyncio.sleep(interval * (0.5 + (j * 0.618) % 1.0))

        async def watch_lag() -> None:
            while time.monotonic() < end:
                t = time.perf_counter()
                await asyncio.sleep(0.02)
                if client_lag is not None:
                    client_lag.append((time.perf_counter() - t - 0.02) * 1e3)

        await asyncio.gather(watch_lag(), *(worker(i) for i in range(clients)))
    return latencies, errors, requests, warmup_s


def _load_processes(
    base: str,
    paths: list[str],
    clients: int,
    duration: float,
    interval: float,
    processes: int = 4,
    server: list[float] | None = None,
    client_lag: list[float] | None = None,
    by_path: dict[str, list[float]] | None = None,
    starts: list[float] | None = None,
) -> tuple[list[float], int, int, float]:
    """The clients spread over a few load processes (one Python process cannot drive 100 clients
    without its own event loop becoming the bottleneck it is meant to measure)."""
    import json

    per = [clients // processes + (1 if i < clients % processes else 0) for i in range(processes)]
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                "-m",
                "bench.bench_service",
                "--load-worker",
                json.dumps({"base": base, "paths": paths, "clients": n, "duration": duration, "interval": interval}),
            ],
            cwd=REPO,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        for n in per
        if n > 0
    ]
    for p in procs:  # all started up before any measures
        assert p.stdout is not None
        if p.stdout.readline().strip() != "ready":
            raise RuntimeError("a load process did not start")
    start_at = time.time() + 2.0  # after every process has opened its connections
    for p in procs:
        assert p.stdin is not None
        p.stdin.write(f"go {start_at}\n")
        p.stdin.flush()
    lat: list[float] = []
    errors = requests = 0
    warm = 0.0
    for p in procs:
        out, _ = p.communicate(timeout=duration + 120)
        r = json.loads(out)
        lat += r["latencies"]
        if by_path is not None:
            for k, v in r["by_path"].items():
                by_path.setdefault(k, []).extend(v)
        if starts is not None:
            starts += r["starts"]
        if server is not None:
            server += r["server_ms"]
        if client_lag is not None:
            client_lag += r["client_lag_ms"]
        errors += r["errors"]
        requests += r["requests"]
        warm = max(warm, r["warmup_s"])
    return lat, errors, requests, warm


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` so far (Linux ``/proc``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _bursts(starts: list[float], latencies: list[float], gap_s: float = 0.1) -> tuple[int, list[float]]:
    """The slowest 1 % of requests and the bursts they were sent in (start times more than
    ``gap_s`` apart; each burst as its start, s after the first request): a few bursts mean a few
    stalls that hit every client at once."""
    lat = np.asarray(latencies)
    t = np.asarray(starts)
    slow = np.sort(t[lat >= np.percentile(lat, 99)])
    if slow.size == 0:
        return 0, []
    firsts = np.concatenate([slow[:1], slow[1:][np.diff(slow) > gap_s]])
    return int(slow.size), [float(v) for v in firsts - t.min()]


def _loop_lag_buckets(base: str) -> dict[float, float]:
    """Cumulative bucket counts of the service's ``lrms_event_loop_lag_seconds`` histogram."""
    import httpx
    from prometheus_client.parser import text_string_to_metric_families

    out: dict[float, float] = {}
    for fam in text_string_to_metric_families(httpx.get(base + "/metrics").text):
        if fam.name == "lrms_event_loop_lag_seconds":
            for sample in fam.samples:
                if sample.name.endswith("_bucket"):
                    out[float(sample.labels["le"])] = sample.value
    return out


def _lag_text(buckets: dict[float, float]) -> str:
    total = buckets.get(float("inf"), 0.0)
    if total <= 0:
        return "no samples"
    over = {ms: total - buckets.get(ms / 1e3, total) for ms in (10, 20, 50)}
    top = min((le for le, c in buckets.items() if c >= total), default=float("inf"))
    return (
        f"{total:.0f} wake-ups, late by > 10 ms: {over[10]:.0f}, > 20 ms: {over[20]:.0f}, > 50 ms: {over[50]:.0f}, "
        f"max <= {top * 1e3:.0f} ms"
    )


def bench_rest(clients: int, duration: float, interval: float, args_processes: int = 4) -> dict[str, Any]:
    import httpx

    from service.cli.serve import LISTENING

    token = "bench"
    with tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "LRMS_API_TOKEN": token}
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "service.cli.main",
                "serve",
                "--port",
                "0",
                "--data",
                tmp,
                "--log-level",
                "warning",
            ],
            cwd=REPO,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            # the service binds the port itself and says where (no free-port race with other processes)
            assert proc.stdout is not None
            base = ""
            for line in proc.stdout:
                if line.startswith(LISTENING):
                    base = line[len(LISTENING) :].strip()
                    break
            if not base:
                proc.kill()
                _, err = proc.communicate(timeout=10)
                raise RuntimeError(f"the service did not start: {err[-2000:]}")
            end = time.monotonic() + 60
            while True:
                try:
                    if httpx.get(base + "/healthz").status_code == 200:
                        break
                except httpx.HTTPError:
                    pass
                if time.monotonic() > end or proc.poll() is not None:
                    proc.kill()
                    _, err = proc.communicate(timeout=10)
                    raise RuntimeError(f"the service did not start: {err[-2000:]}")
                time.sleep(0.2)
            paths = ["/healthz", "/api/v1/rig", "/api/v1/measurements?limit=20"]
            # the load generator must not measure its own garbage collector: this process holds
            # numpy, scipy and the simulator from the ingest benchmark
            gc.collect()
            gc.freeze()
            idle, idle_err, _, _ = asyncio.run(_load(base, paths, 1, 3.0))
            # baseline 2: the same load with the rig idle (what the sweep adds is the difference)
            cpu0, t0 = _cpu_s(proc.pid), time.monotonic()
            quiet, quiet_err, quiet_n, _ = _load_processes(
                base, paths, clients, min(duration, 10.0), interval, args_processes
            )
            quiet_cpu = (_cpu_s(proc.pid) - cpu0) / (time.monotonic() - t0)
            quiet_cpu_per_req = (_cpu_s(proc.pid) - cpu0) / max(quiet_n, 1)
            speed = 90.0 / max(duration, 1.0)  # the sweep lasts about the load's duration
            auth = {"Authorization": f"Bearer {token}"}
            r = httpx.post(
                base + "/api/v1/measurements",
                headers=auth,
                json={"target": "cylinder", "sweep": {"speed_deg_s": speed}},
            )
            mid = r.json()["id"]
            while httpx.get(f"{base}/api/v1/measurements/{mid}").json()["state"] == "queued":
                time.sleep(0.05)
            paths.append(f"/api/v1/measurements/{mid}")
            server_ms: list[float] = []
            client_lag: list[float] = []
            by_path: dict[str, list[float]] = {}
            starts: list[float] = []
            lag0 = _loop_lag_buckets(base)
            cpu0, t0 = _cpu_s(proc.pid), time.monotonic()
            lat, errors, n, warmup_s = _load_processes(
                base, paths, clients, duration, interval, args_processes, server_ms, client_lag, by_path, starts
            )
            sweep_cpu = (_cpu_s(proc.pid) - cpu0) / (time.monotonic() - t0)
            lag1 = _loop_lag_buckets(base)
            while True:
                m = httpx.get(f"{base}/api/v1/measurements/{mid}").json()
                if m["state"] in ("done", "failed", "cancelled"):
                    break
                time.sleep(0.5)
        finally:
            proc.terminate()
            proc.wait(30)
    res = m.get("result") or {}
    stats = res.get("scanner_stats", {})
    lat_a = np.asarray(lat) * 1e3
    idle_a = np.asarray(idle) * 1e3
    return {
        "clients": clients,
        "duration_s": duration,
        "interval_s": interval,
        "requests": n,
        "errors": errors + idle_err + quiet_err,
        "quiet_p50_ms": float(np.percentile(np.asarray(quiet) * 1e3, 50)),
        "quiet_p99_ms": float(np.percentile(np.asarray(quiet) * 1e3, 99)),
        "p50_ms": float(np.percentile(lat_a, 50)),
        "p99_ms": float(np.percentile(lat_a, 99)),
        "server_p50_ms": float(np.nanpercentile(server_ms, 50)),
        "server_p99_ms": float(np.nanpercentile(server_ms, 99)),
        "server_max_ms": float(np.nanmax(server_ms)),
        "client_lag_p99_ms": float(np.percentile(client_lag, 99)),
        "server_cpu": sweep_cpu,
        "slow_bursts": _bursts(starts, lat),
        "p99_by_path_ms": {
            k.replace(f"/{mid}", "/{id}"): float(np.percentile(np.asarray(v) * 1e3, 99)) for k, v in by_path.items()
        },
        "quiet_cpu": quiet_cpu,
        "quiet_cpu_ms_per_request": quiet_cpu_per_req * 1e3,
        "client_lag_max_ms": float(np.max(client_lag)),
        "server_lag": {le: lag1[le] - lag0.get(le, 0.0) for le in lag1},
        "processes": args_processes,
        "warmup_s": warmup_s,
        "max_ms": float(lat_a.max()),
        "idle_p50_ms": float(np.percentile(idle_a, 50)),
        "idle_p99_ms": float(np.percentile(idle_a, 99)),
        "measurement_state": m["state"],
        "measurement_error": m.get("error"),
        "scans_received": res.get("sweep", {}).get("scans_received"),
        "scans_dropped": (res.get("sweep", {}).get("scans_missing", 0) or 0) + (stats.get("queue_drops", 0) or 0),
        "scans_missing": res.get("sweep", {}).get("scans_missing", 0) or 0,
        "queue_drops": stats.get("queue_drops", 0) or 0,
        "diameter_mm": (res.get("diameter_m") or float("nan")) * 1e3,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--clients", type=int, default=100)
    parser.add_argument("--duration", type=float, default=30.0)
    parser.add_argument("--scans", type=int, default=500)
    parser.add_argument(
        "--interval", type=float, default=0.5, help="each client's mean pause between requests (s); 0 = closed loop"
    )
    parser.add_argument("--processes", type=int, default=4, help="load-generator processes the clients are spread over")
    parser.add_argument("--skip-rest", action="store_true")
    parser.add_argument("--skip-ingest", action="store_true")
    parser.add_argument("--load-worker", metavar="JSON", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.load_worker:
        import json

        w = json.loads(args.load_worker)
        srv: list[float] = []
        lag: list[float] = []
        by_path: dict[str, list[float]] = {}
        starts: list[float] = []
        lat, err, n, warm = asyncio.run(
            _load(w["base"], w["paths"], w["clients"], w["duration"], w["interval"], srv, True, lag, by_path, starts)
        )
        out = {
            "latencies": lat,
            "errors": err,
            "requests": n,
            "warmup_s": warm,
            "server_ms": srv,
            "client_lag_ms": lag,
            "by_path": by_path,
            "starts": starts,
        }
        print(json.dumps(out))
        return 0
    print(f"machine: {os.cpu_count()} cores, Python {sys.version.split()[0]}")
    rt = 25.0  # LMS100 scans/s at 0.25 deg (1081 beams)
    ing = bench_ingest(args.scans) if not args.skip_ingest else None
    if ing is not None:
        print(
            f"ingest: {ing['scans']} scans x 1081 beams: decode only {ing['decode_scans_per_s']:.0f} scans/s "
            f"(baseline), decode+record+log+map {ing['pipeline_scans_per_s']:.0f} scans/s (median of "
            f"{', '.join(f'{v:.0f}' for v in ing['pipeline_runs_scans_per_s'])}) = "
            f"{ing['pipeline_scans_per_s'] / rt:.0f}x the sensor's real-time rate (goal >= 100x), "
            f"{ing['pipeline_scans_per_s'] / ing['decode_scans_per_s']:.2f}x the decode-only rate; "
            f"MCAP {ing['mcap_bytes_per_scan'] / 1024:.1f} KiB/scan"
        )
    if not args.skip_rest:
        r = bench_rest(args.clients, args.duration, args.interval, args.processes)
        mode = f"each polling every ~{r['interval_s']:g} s" if r["interval_s"] > 0 else "closed loop"
        print(
            f"REST: {r['clients']} clients ({mode}) for {r['duration_s']:.0f} s during a sweep: "
            f"{r['requests']} requests ({r['requests'] / r['duration_s']:.0f}/s), "
            f"{r['errors']} errors, p50 {r['p50_ms']:.1f} ms, p99 {r['p99_ms']:.1f} ms (goal <= 50 ms), "
            f"max {r['max_ms']:.0f} ms (clients in {r['processes']} processes); time in the app (Server-Timing): "
            f"p50 {r['server_p50_ms']:.2f} ms, p99 {r['server_p99_ms']:.2f} ms, max {r['server_max_ms']:.0f} ms; "
            f"the service process used {r['server_cpu'] * 100:.0f} % of a core (rig idle, same load: "
            f"{r['quiet_cpu'] * 100:.0f} %, {r['quiet_cpu_ms_per_request']:.2f} ms CPU per request); "
            f"the slowest 1 % ({r['slow_bursts'][0]} requests) were sent in {len(r['slow_bursts'][1])} bursts "
            f"(at {', '.join(f'{v:.1f}' for v in r['slow_bursts'][1][:10])} s); "
            f"p99 by endpoint: {', '.join(f'{k} {v:.0f} ms' for k, v in r['p99_by_path_ms'].items())}; "
            f"the API's event loop (20 ms sleeps): {_lag_text(r['server_lag'])}; the load processes' own loops: "
            f"late by p99 {r['client_lag_p99_ms']:.1f} ms, max {r['client_lag_max_ms']:.0f} ms; "
            f"the {r['clients']} connections took {r['warmup_s']:.2f} s to open; "
            f"one idle client: p50 {r['idle_p50_ms']:.1f} ms, p99 {r['idle_p99_ms']:.1f} ms "
            f"(p99 ratio {r['p99_ms'] / r['idle_p99_ms']:.1f}x); the same load with the rig idle: "
            f"p50 {r['quiet_p50_ms']:.1f} ms, p99 {r['quiet_p99_ms']:.1f} ms"
        )
        print(
            f"sweep under load: {r['measurement_state']} {r['measurement_error'] or ''} "
            f"scans received {r['scans_received']}, dropped {r['scans_dropped']} (goal 0: "
            f"{r['scans_missing']} scan-counter gaps, i.e. never sent or lost on the way; "
            f"{r['queue_drops']} dropped by the client's queue), "
            f"diameter {r['diameter_mm']:.2f} mm"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
