"""``lrms serve``: the acquisition service (REST under /api/v1) for a rig, by default the simulated one."""

from __future__ import annotations

import argparse

HELP = "run the acquisition service (REST API, job queue, schedules) for a rig"
LISTENING = "lrms serve: listening on"
"""Start of the stdout line that gives the service's URL (``http://HOST:PORT``) once its socket listens."""


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="RIG.toml", help="rig configuration (default: the simulated seed 003 rig)")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    parser.add_argument(
        "--port",
        type=int,
        default=8000,
        help="TCP port (default 8000; 0 = any free port: the 'lrms serve: listening on URL' line on stdout gives it)",
    )
    parser.add_argument("--data", metavar="DIR", help="storage folder (overrides [storage] dir)")
    parser.add_argument("--log-level", default="info", choices=("critical", "error", "warning", "info", "debug"))


def run(args: argparse.Namespace) -> int:
    import os

    # one BLAS thread: the fits are then bit-for-bit repeatable (lrms replay), and the rig's
    # threads keep the cores
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    import contextlib
    import copy
    import logging
    import signal
    import socket

    import uvicorn

    from service.api import create_app
    from service.config import load_config
    from service.errors import ServiceError
    from service.rig import build_service

    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    cfg = load_config(args.config, storage_dir=args.data)
    svc, rig = build_service(cfg, log_level=args.log_level)  # the rig in its own process (service.rigproc)

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
        # bound and listening before the address is announced: with --port 0 the line below is how
        # a caller learns the port (connections made after it wait in the backlog until uvicorn runs)
        family = socket.AF_INET6 if ":" in args.host else socket.AF_INET
        try:
            sock = socket.create_server((args.host, args.port), family=family)
        except OSError as exc:
            raise ServiceError(f"cannot listen on {args.host} port {args.port}: {exc}") from exc
        port = int(sock.getsockname()[1])
        shown = f"[{args.host}]" if family == socket.AF_INET6 else args.host
        print(f"{LISTENING} http://{shown}:{port}", flush=True)
        # uvicorn's access log goes to stderr too: stdout carries only the lines above, so a caller
        # that reads the listening line and then leaves the pipe alone cannot block the server
        log_config = copy.deepcopy(uvicorn.config.LOGGING_CONFIG)
        log_config["handlers"]["access"]["stream"] = "ext://sys.stderr"
        server = uvicorn.Server(
            uvicorn.Config(app, host=args.host, port=port, log_level=args.log_level, log_config=log_config)
        )
        with contextlib.suppress(KeyboardInterrupt):  # as uvicorn.run: Ctrl-C is a clean stop
            server.run(sockets=[sock])
        if not server.started:
            raise ServiceError("the HTTP server did not start")
    finally:
        rig.close()
    return 0
