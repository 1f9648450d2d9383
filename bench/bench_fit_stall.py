"""How long mapping and the fit keep a real-time thread of the same process waiting.

Run: ``.venv/bin/lrms measure --target cylinder --out run.mcap`` once, then
``.venv/bin/python -m bench.bench_fit_stall run.mcap [--monte-carlo N]``.

A thread sleeping 10 ms in a loop stands in for the drive's heartbeat thread (100 ms period; the
drive's watchdog faults after 500 ms). Its lateness (wake-up time minus 10 ms) is measured in
three cases of the same run: idle (the baseline: the machine's own scheduling), while
``lrms replay`` of the log (decode, mapping, fit; with ``--monte-carlo`` refits) runs in the
same interpreter, and while the same replay runs in a spawned worker process (as the rig
process does it: ``service.rig.Rig._finish``). Ratios are against the idle case.
"""

from __future__ import annotations

import argparse
import multiprocessing
import threading
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from typing import Any


def _replay(path: str, monte_carlo: int) -> float:
    import service.rig as rig
    from service.replay import replay

    orig = rig.finish_measurement

    def patched(recorder: Any, config: Any, request: Any, sweep: Any, t0: int, t1: int | None) -> Any:
        options = request.options.model_copy(update={"monte_carlo": monte_carlo})
        return orig(recorder, config, request.model_copy(update={"options": options}), sweep, t0, t1)

    rig.finish_measurement = patched  # type: ignore[assignment]
    t = time.perf_counter()
    try:
        replay(path)
    finally:
        rig.finish_measurement = orig
    return time.perf_counter() - t


def _lateness_during(work: Callable[[], object]) -> list[float]:
    late: list[float] = []
    stop = threading.Event()

    def tick() -> None:
        while not stop.is_set():
            t = time.perf_counter()
            time.sleep(0.01)
            late.append(time.perf_counter() - t - 0.01)

    th = threading.Thread(target=tick)
    th.start()
    try:
        work()
    finally:
        stop.set()
        th.join()
    return sorted(late)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("log", help="a raw log (lrms measure --out run.mcap)")
    parser.add_argument("--monte-carlo", type=int, default=0)
    parser.add_argument("--idle-s", type=float, default=5.0)
    args = parser.parse_args()
    _replay(args.log, 0)  # warm-up: imports and first calls
    pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"))
    pool.submit(_replay, args.log, 0).result()  # the worker warmed up the same way
    cases = {
        "idle": _lateness_during(lambda: time.sleep(args.idle_s)),
        "fit in this process": _lateness_during(lambda: _replay(args.log, args.monte_carlo)),
        "fit in a worker process": _lateness_during(lambda: pool.submit(_replay, args.log, args.monte_carlo).result()),
    }
    pool.shutdown()
    base = cases["idle"][-1]
    print(f"lateness of a 10 ms sleep loop (monte_carlo = {args.monte_carlo})")
    print(f"{'case':<26} {'ticks':>6} {'p50 ms':>8} {'p99 ms':>8} {'max ms':>8} {'max / idle max':>15}")
    for name, late in cases.items():
        p50, p99 = late[len(late) // 2], late[min(len(late) - 1, int(len(late) * 0.99))]
        row = f"{name:<26} {len(late):>6} {p50 * 1e3:>8.2f} {p99 * 1e3:>8.2f} {late[-1] * 1e3:>8.1f}"
        print(f"{row} {late[-1] / base:>15.1f}")


if __name__ == "__main__":
    main()
