"""``lrms serve``: the acquisition service (REST under /api/v1) for a rig, by default the simulated one."""

from __future__ import annotations

import argparse
import ipaddress
import socket
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from service.config import RigConfig, Role

HELP = "run the acquisition service (REST API, job queue, schedules) for a rig"
LISTENING = "lrms serve: listening on"
"""Start of the stdout line that gives the service's URL (``http://HOST:PORT``, ``https://`` with TLS)
once its socket listens."""
WARNING = "lrms serve: WARNING:"
"""Start of the stderr lines that warn of a listening address beyond loopback without TLS or read token."""


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
    parser.add_argument(
        "--tls-cert", metavar="CERT.pem", help="serve HTTPS with this certificate (overrides [api] tls_cert)"
    )
    parser.add_argument(
        "--tls-key", metavar="KEY.pem", help="the certificate's private key, unencrypted (overrides [api] tls_key)"
    )


def is_loopback(host: str) -> bool:
    """Whether ``host`` (an address or a name) is on this machine only; a name is resolved, and one
    that does not resolve counts as beyond loopback."""
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        pass
    try:
        infos = socket.getaddrinfo(host, None)
    except OSError:
        return False
    return bool(infos) and all(ipaddress.ip_address(str(i[4][0]).split("%")[0]).is_loopback for i in infos)


def exposure_warnings(host: str, config: RigConfig, tls: bool) -> list[str]:
    """The warnings for listening on ``host``: none on loopback; beyond it, one for a missing TLS
    certificate and one for reads that need no token (write endpoints always need one)."""
    if is_loopback(host):
        return []
    out = []
    if not tls:
        out.append(
            f"listening on {host}, beyond loopback, without TLS: bearer tokens and results cross the network "
            "in clear text (give --tls-cert and --tls-key, or [api] tls_cert and tls_key)"
        )
    if config.auth.read == "open":
        out.append(
            f'listening on {host}, beyond loopback, without a token for reads ([auth] read = "open"): '
            "results, raw logs and the devices' addresses are open to anyone on the network"
        )
    return out


def tls_files(args: argparse.Namespace, config: RigConfig) -> tuple[Path, Path] | None:
    """The certificate and key to serve HTTPS with (command line over config), checked to load."""
    import ssl

    from service.errors import ServiceError

    if (args.tls_cert is None) != (args.tls_key is None):
        raise ServiceError("--tls-cert and --tls-key go together: give both or neither")
    if args.tls_cert is not None:
        cert, key = Path(args.tls_cert), Path(args.tls_key)
    elif config.api.tls_cert is not None and config.api.tls_key is not None:
        cert, key = config.api.tls_cert, config.api.tls_key
    else:
        return None
    try:
        # password: an encrypted key fails here instead of prompting on the terminal
        ssl.create_default_context(ssl.Purpose.CLIENT_AUTH).load_cert_chain(cert, key, password=lambda: b"")
    except (OSError, ssl.SSLError) as exc:
        raise ServiceError(f"cannot load the TLS certificate {cert} with key {key}: {exc}") from None
    return cert, key


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

    import uvicorn

    from service.api import create_app
    from service.config import load_config
    from service.db.engine import shown as shown_url
    from service.errors import ServiceError
    from service.rig import build_service

    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    cfg = load_config(args.config, storage_dir=args.data)
    tls = tls_files(args, cfg)
    for warning in exposure_warnings(args.host, cfg, tls is not None):
        print(f"{WARNING} {warning}", file=sys.stderr, flush=True)
        logging.getLogger("lrms.serve").warning("%s", warning)
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
        print(f"lrms serve: results in {shown_url(cfg.storage.db_url)} as rig id {cfg.storage.rig_id}", flush=True)
        print(f"lrms serve: {auth_summary(cfg)}", flush=True)
        # bound and listening before the address is announced: with --port 0 the line below is how
        # a caller learns the port (connections made after it wait in the backlog until uvicorn runs)
        family = socket.AF_INET6 if ":" in args.host else socket.AF_INET
        try:
            sock = socket.create_server((args.host, args.port), family=family)
        except OSError as exc:
            raise ServiceError(f"cannot listen on {args.host} port {args.port}: {exc}") from exc
        port = int(sock.getsockname()[1])
        shown = f"[{args.host}]" if family == socket.AF_INET6 else args.host
        print(f"{LISTENING} {'https' if tls else 'http'}://{shown}:{port}", flush=True)
        # uvicorn's access log goes to stderr too: stdout carries only the lines above, so a caller
        # that reads the listening line and then leaves the pipe alone cannot block the server
        log_config = copy.deepcopy(uvicorn.config.LOGGING_CONFIG)
        log_config["handlers"]["access"]["stream"] = "ext://sys.stderr"
        server = uvicorn.Server(
            uvicorn.Config(
                app,
                host=args.host,
                port=port,
                log_level=args.log_level,
                log_config=log_config,
                ssl_certfile=None if tls is None else str(tls[0]),
                ssl_keyfile=None if tls is None else str(tls[1]),
            )
        )
        with contextlib.suppress(KeyboardInterrupt):  # as uvicorn.run: Ctrl-C is a clean stop
            server.run(sockets=[sock])
        if not server.started:
            raise ServiceError("the HTTP server did not start")
    finally:
        rig.close()
    return 0


def auth_summary(config: RigConfig) -> str:
    """Which tokens are configured (never their values) and whether reads need one."""
    roles: tuple[Role, ...] = ("operator", "admin", "read")
    have = [r for r in roles if config.role_token(r) is not None]
    reads = "reads need a token" if config.auth.read == "token" else "reads are open"
    tokens = f"tokens configured: {', '.join(have)}" if have else "no token configured"
    writes = "" if {"operator", "admin"} & set(have) else " (write endpoints are disabled)"
    if config.auth.read == "token" and not have:
        reads += " (so every read is refused)"
    return f"auth: {reads}; {tokens}{writes}"
