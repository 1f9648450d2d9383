"""Throughput of ``lrms reprocess``: archived sweeps re-fitted serially, on 1 and on 2 Dask workers.

Run: ``.venv/bin/python -m bench.bench_reprocess [--sweeps 200] [--distinct 10] [--full 2] [--dir DIR]``.

The archive is made once (into a temporary folder, or ``--dir`` to keep and reuse it): ``--distinct``
short sweeps recorded on the built-in simulated rig (seed 003's cylinder, -5..20 deg at 20 deg/s,
about 32 scans and 20 000 mapped points each; :data:`service.simarchive.SHORT_SWEEP`), then copied
under new measurement ids up to ``--sweeps`` (the simulator runs in real time, 3 s a sweep). The
same archive is then re-processed three ways in this run, each into a result-version store of
its own (so each really fits every sweep): the serial loop in this process (the baseline), a
:class:`distributed.LocalCluster` of 1 worker process and one of 2 (one thread each; cluster
start-up timed apart). Printed: wall time, throughput (sweeps/s) and its ratio to the serial
loop, the per-sweep cost (CPU time in the task: read, SHA-256, decode, mapping, fit), the cores
the run kept busy (task CPU / wall: on an idle machine about 1 for the serial loop and N for N
workers) and the load average when the mode started.
``--full N`` also records N sweeps of the default length (-20..70 deg at 10 deg/s) and prints
their per-sweep cost, the figure docs/fleet.md scales up.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path
from typing import Any

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")


def _run(label: str, measurements: list[Any], executor: Any, store_path: Path) -> dict[str, float]:
    from service import reprocess as rp
    from service.store import Store
    from service.versionstore import VersionStore

    for suffix in ("", "-wal", "-shm"):  # a store of its own, empty: every sweep is fitted
        Path(f"{store_path}{suffix}").unlink(missing_ok=True)
    engine = Store(store_path).engine  # the result store's schema, migrated (result_versions: 0005)
    store = VersionStore(engine)
    load = os.getloadavg()[0]
    t = time.perf_counter()
    summary = rp.reprocess(store, measurements, executor)
    wall = time.perf_counter() - t
    engine.dispose()
    if summary.failed or summary.done != len(measurements):
        raise SystemExit(f"{label}: {summary.done} done, failed: {summary.failed[:3]}")
    n = len(measurements)
    return {"wall": wall, "rate": n / wall, "cpu": summary.cpu_s / n, "load": load}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sweeps", type=int, default=200)
    ap.add_argument("--distinct", type=int, default=10, help="sweeps really recorded (the rest are copies)")
    ap.add_argument("--full", type=int, default=2, help="full-length sweeps recorded for their per-sweep cost")
    ap.add_argument("--dir", help="archive folder (kept; reused when it holds enough sweeps)")
    args = ap.parse_args()

    from service import reprocess as rp
    from service import simarchive

    with tempfile.TemporaryDirectory(prefix="lrms-bench-reprocess-") as tmp:
        root = Path(args.dir) if args.dir else Path(tmp) / "archive"
        cfg = simarchive.sim_config(root)
        engine = rp.result_engine(cfg)
        have = len(rp.archived_measurements(engine)) if cfg.storage.db_path.exists() else 0
        if have < args.sweeps:
            t = time.perf_counter()
            if have == 0:
                simarchive.record(root, args.distinct)
            simarchive.replicate(root, args.sweeps)
            print(
                f"archive: {args.distinct} short sweeps recorded, copied to {args.sweeps}:"
                f" {time.perf_counter() - t:.0f} s"
            )
        measurements = rp.archived_measurements(engine)[: args.sweeps]
        engine.dispose()
        n = len(measurements)
        size = sum(os.path.getsize(m.raw_path) for m in measurements) / n
        print(f"{n} archived sweeps ({simarchive.SHORT_SWEEP}), raw logs {size / 1e6:.2f} MB each on average")
        print(f"machine: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f} at the start")

        rows: list[tuple[str, dict[str, float]]] = [
            ("serial loop", _run("serial", measurements, rp.serial_executor, root / "v0.sqlite"))
        ]
        for workers in (1, 2):
            t = time.perf_counter()
            with rp.dask_client(None, workers) as client:
                client.run(lambda: __import__("service.replay"))  # imports on every worker: not part of the timing
                start = time.perf_counter() - t
                res = _run(f"dask {workers}", measurements, rp.dask_executor(client), root / f"v{workers}.sqlite")
            rows.append((f"dask, {workers} worker{'s' if workers > 1 else ''}", res))
            print(f"(LocalCluster of {workers} started and warmed up in {start:.1f} s)")

        base = rows[0][1]["rate"]
        print()
        print(f"{'mode':<20} {'wall s':>8} {'sweeps/s':>9} {'ratio':>6} {'CPU s/sweep':>12} {'cores':>10} {'load':>5}")
        for label, r in rows:
            print(
                f"{label:<20} {r['wall']:8.1f} {r['rate']:9.2f} {r['rate'] / base:6.2f}"
                f" {r['cpu']:12.3f} {r['cpu'] * n / r['wall']:10.2f} {r['load']:5.2f}"
            )

        if args.full > 0:
            from service.reprocess import Task, reprocess_one

            full = simarchive.record(root / "full", args.full, sweep={})
            costs = []
            for m in full:
                assert m.raw_path is not None
                out = reprocess_one(Task(m.id, m.raw_path, software_version=__import__("lrms").__version__))
                if out.status != "done":
                    raise SystemExit(f"full sweep {m.id}: {out.reason}")
                costs.append(out.cpu_s)
            mb = sum(os.path.getsize(m.raw_path or "") for m in full) / len(full) / 1e6
            print()
            print(
                f"full-length sweeps (-20..70 deg at 10 deg/s), {len(full)}: CPU s/sweep "
                + ", ".join(f"{c:.3f}" for c in costs)
                + f"; raw log {mb:.2f} MB each"
            )


if __name__ == "__main__":
    main()
