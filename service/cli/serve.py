"""``lrms serve``: the acquisition service (REST under /api/v1) for a rig, by default the simulated one."""

from __future__ import annotations

import argparse

HELP = "run the acquisition service (REST API, job queue, schedules) for a rig"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="RIG.toml", help="rig configuration (default: the simulated seed 003 rig)")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=8000, help="TCP port (default 8000; 0 = any free port)")
    parser.add_argument("--data", metavar="DIR", help="storage folder (overrides [storage] dir)")
    parser.add_argument("--log-level", default="info", choices=("critical", "error", "warning", "info", "debug"))


def run(args: argparse.Namespace) -> int:
    import os

    # one BLAS thread: the fits are then bit-for-bit repeatable (lrms replay), and the rig's
    # threads keep the cores
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    import logging
    import signal

    import uvicorn

    from service.api import create_app
    from service.config import load_config
    from service.rig import build_service

    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    cfg = load_config(args.config, storage_dir=args.data)
    svc, rig = build_service(cfg)

    def terminated(signum: int, frame: object) -> None:
        # uvicorn shuts down gracefully on SIGTERM, then raises the signal again with the handler
        # it found (this one): exit through ``finally`` so the rig is closed (the drive stops
        # watching our heartbeat instead of faulting when it ends)
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, terminated)
    try:
        app = create_app(svc)
        where = "simulated rig" if cfg.is_sim else f"scanner {rig.scanner_url}, motor {rig.motor_url}"
        print(f"lrms serve: {cfg.name} ({where}); data in {cfg.storage.dir}", flush=True)
        if svc.token() is None:
            print("write endpoints are disabled: set [auth] token or LRMS_API_TOKEN", flush=True)
        uvicorn.run(app, host=args.host, port=args.port, log_level=args.log_level)
    finally:
        rig.close()
    return 0
