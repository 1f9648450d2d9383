"""``/api/v1/rig``: the rig's configuration and its devices' state."""

from __future__ import annotations

import time
from typing import Any

from fastapi import APIRouter, HTTPException, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.encoders import jsonable_encoder

from service.api.core import JsonBytes, Service
from service.api.deps import OPERATE, READ, READ_RESPONSES, WRITE_RESPONSES, ServiceDep
from service.api.errors import responses
from service.api.schemas import RigOut

router = APIRouter(tags=["rig"], dependencies=READ, responses=READ_RESPONSES)

_LIVE_PERIOD_S = 0.25


def _static(service: Service) -> dict[str, Any]:
    """The configuration part (it does not change while the app runs)."""
    cfg = service.config
    return {
        "name": cfg.name,
        "simulated": cfg.is_sim,
        "scanner_url": cfg.scanner.url,
        "motor_url": cfg.motor.url,
        "kinematics": cfg.kinematics,
        "noise": cfg.noise.model_dump(mode="json"),
        "sweep_defaults": cfg.sweep.model_dump(mode="json"),
        "fit_defaults": cfg.fit.model_dump(mode="json"),
        "motor_limits": cfg.motor.model_dump(mode="json", exclude={"url", "errors"}),
        "min_schedule_interval_s": cfg.schedules.min_interval_s,
        "sim": cfg.sim.model_dump(mode="json") if cfg.sim is not None else None,
    }


@router.get("/rig", response_class=JsonBytes, response_model=RigOut)
async def rig(service: ServiceDep) -> Response:
    """Configuration and device state. The device part is read at most every 0.25 s (on a
    worker thread, as a driver may block); requests in between get that reading."""
    live = service.rig_live
    if time.monotonic() - live.read_at >= _LIVE_PERIOD_S:
        async with live.lock:  # one device query for all the requests that found it stale
            if time.monotonic() - live.read_at >= _LIVE_PERIOD_S:
                live.info = await run_in_threadpool(service.rig_info)
                live.read_at = time.monotonic()
    write_enabled, busy = service.write_enabled(), service.runner.running_id is not None
    key = (live.read_at, write_enabled, busy)
    if live.body is None or live.body[0] != key:
        info = {**_static(service), "write_enabled": write_enabled, "busy": busy, **live.info}
        # through the response model, so the body is what the schema says (non-finite numbers: null;
        # device fields the drivers did not report are left out)
        live.body = (key, RigOut.model_validate(jsonable_encoder(info)).model_dump_json(exclude_unset=True).encode())
    return JsonBytes(live.body[1])


@router.post(
    "/rig/reset",
    dependencies=OPERATE,
    responses={**WRITE_RESPONSES, **responses(404, 409)},
)
def reset(service: ServiceDep) -> dict[str, Any]:
    """Clear a drive fault (CiA 402 fault reset) in the rig process: ``{"ok", "error", "motor"}``.
    409 while a measurement runs, or when the drive refuses the reset."""
    if service.rig_reset is None:
        raise HTTPException(404, "this service has no rig to reset")
    out = service.rig_reset()
    if not out["ok"]:
        raise HTTPException(409, f"drive reset failed: {out['error']}")
    service.rig_live.read_at = -1e9  # GET /rig reads the new state
    return out
