"""A simulated archive of measurements: raw logs and result store, for the tests and benchmarks of
``lrms reprocess``.

:func:`record` runs real measurements on the built-in simulated rig (in this process, on a
python-can virtual bus; the scanner on TCP 127.0.0.1), through the service's job runner, so the
store rows and raw logs are exactly what a rig writes. The simulator runs in real time (about
3 s per :data:`SHORT_SWEEP`), so :func:`replicate` fills a larger archive with copies of recorded
logs under new measurement ids (through :class:`service.store.Store`'s own calls).
"""

from __future__ import annotations

import shutil
import time
from importlib import resources
from pathlib import Path
from typing import Any

from service.config import DEFAULT_RIG, RigConfig, parse_toml
from service.errors import ServiceError
from service.store import Measurement, Store

#: A short sweep over seed 003's cylinder (-5..20 deg at 20 deg/s: about 32 scans, 3 s).
SHORT_SWEEP: dict[str, Any] = {"start_deg": -5.0, "stop_deg": 20.0, "speed_deg_s": 20.0}


def sim_config(storage_dir: str | Path, seed: int = 0) -> RigConfig:
    """The built-in simulated rig in this process (virtual CAN bus), storing under ``storage_dir``."""
    text = resources.files("service").joinpath(DEFAULT_RIG).read_text(encoding="utf-8")
    text = text.replace("process = true ", "process = false").replace('can = "socketcand"', 'can = "virtual"')
    text = text.replace("seed = 0 ", f"seed = {int(seed)} ")
    cfg = parse_toml(text, source="(simulated archive rig)")
    storage = cfg.storage.model_copy(update={"dir": Path(storage_dir).resolve()})
    return cfg.model_copy(update={"storage": storage})


def record(
    storage_dir: str | Path, n: int, sweep: dict[str, Any] | None = None, seed: int = 0, timeout_s: float = 120.0
) -> list[Measurement]:
    """``n`` cylinder measurements of ``sweep`` (default :data:`SHORT_SWEEP`; ``{}``: the rig's
    default sweep) on the simulated rig."""
    from service.models import MeasurementRequest
    from service.rig import build_service

    cfg = sim_config(storage_dir, seed)
    request = MeasurementRequest.model_validate(
        {"target": "cylinder", "sweep": SHORT_SWEEP if sweep is None else sweep}
    )
    svc, rig = build_service(cfg, isolate=False)
    out: list[Measurement] = []
    errors: list[str] = []
    try:
        svc.start()
        while len(out) < n:
            # one at a time; on a loaded machine the drive's heartbeat can be starved into a fault:
            # reset it and measure again (the failed measurement stays in the store, as on a rig)
            if len(errors) > 2 * n + 2:
                raise ServiceError(f"simulated measurements keep failing: {errors[-1]}")
            mid = svc.runner.submit(request).id
            end = time.monotonic() + timeout_s
            while (m := svc.store.get(mid)).state not in ("done", "failed", "cancelled"):
                if time.monotonic() > end:
                    raise ServiceError("a simulated measurement did not finish in time")
                time.sleep(0.1)
            if m.state == "done":
                out.append(m)
            else:
                errors.append(f"{m.state}: {m.error}")
                rig.reset()
    finally:
        svc.stop()
        rig.close()
    return out


def replicate(storage_dir: str | Path, total: int) -> list[Measurement]:
    """Grow the archive to ``total`` done measurements with copies of its recorded raw logs (new
    ids, logs copied to ``raw/<id>.mcap``, the original's request and result)."""
    cfg = sim_config(storage_dir)
    store = Store(cfg.storage.db_path)
    try:
        done = [m for m in store.list_measurements("done", limit=1_000_000) if m.raw_path and m.result]
        if not done:
            raise ServiceError(f"no recorded measurement under {storage_dir} to replicate")
        done.sort(key=lambda m: m.created_at)
        out = list(done)
        i = 0
        while len(out) < total:
            src = done[i % len(done)]
            i += 1
            m = store.create_measurement(src.request)
            raw = cfg.storage.raw_dir / f"{m.id}.mcap"
            assert src.raw_path is not None and src.result is not None
            shutil.copyfile(src.raw_path, raw)
            store.start(m.id)
            store.set_paths(m.id, raw_path=str(raw))
            out.append(store.finish(m.id, {**src.result, "measurement_id": m.id}))
        return out[:total]
    finally:
        store.close()
