"""``lrms measure``: one measurement on a rig (default: the simulated seed 003 rig), result as JSON."""

from __future__ import annotations

import argparse

HELP = "run one sweep and fit on a rig and print the result as JSON"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="RIG.toml", help="rig configuration (default: the simulated seed 003 rig)")
    parser.add_argument("--target", required=True, choices=("cylinder", "elbow"), help="what to fit")
    parser.add_argument("--out", metavar="RUN.mcap", help="also copy the raw log (MCAP) here")
    parser.add_argument("--cloud", metavar="CLOUD.ply", help="also copy the mapped cloud (PLY) here")
    parser.add_argument("--plot", metavar="OUT.png", help="plot the cloud in the region of interest and the fit")
    parser.add_argument("--start", type=float, metavar="DEG", help="first scan-plane angle beta (deg)")
    parser.add_argument("--stop", type=float, metavar="DEG", help="last scan-plane angle beta (deg)")
    parser.add_argument("--speed", type=float, metavar="DEG_S", help="sweep speed (deg/s)")
    parser.add_argument("--mode", choices=("constant", "step"), help="constant speed or step-and-scan")
    parser.add_argument("--k", type=float, help="coverage factor of the critical-point interval")
    parser.add_argument("--monte-carlo", type=int, default=0, metavar="N", help="Monte Carlo refits (0 = off)")
    parser.add_argument("--data", metavar="DIR", help="storage folder (overrides [storage] dir)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument(
        "--server",
        metavar="URL",
        help="measure on a running 'lrms serve' at this base URL (e.g. http://127.0.0.1:8000) instead of "
        "starting a rig here; not with --config, --data or --plot",
    )
    parser.add_argument(
        "--token",
        help="with --server: the operator or admin bearer token "
        "(default: $LRMS_OPERATOR_TOKEN, $LRMS_ADMIN_TOKEN, $LRMS_API_TOKEN, the first one set)",
    )
    parser.add_argument(
        "--timeout",
        type=float,
        metavar="SECONDS",
        help="with --server: seconds to wait for each answer of the service (default 30)",
    )
    parser.add_argument(
        "--wait",
        type=float,
        metavar="SECONDS",
        help="with --server: give up after this many seconds from the request (the measurement is "
        "then cancelled on the service and the command fails; default: wait until it ends)",
    )


def progress_bar(fraction: float, message: str, width: int = 30) -> str:
    """The one-line progress bar (``\\r`` first: it overwrites itself on stderr)."""
    n = round(max(0.0, min(1.0, fraction)) * width)
    return f"\r[{'#' * n}{'.' * (width - n)}] {fraction * 100:5.1f}% {message[:50]:<50}"


def request_body(args: argparse.Namespace) -> dict[str, object]:
    """The measurement request (``MeasurementRequest``'s JSON) of the command's options."""
    sweep = {
        k: v
        for k, v in (
            ("start_deg", args.start),
            ("stop_deg", args.stop),
            ("speed_deg_s", args.speed),
            ("mode", args.mode),
        )
        if v is not None
    }
    options: dict[str, object] = {"monte_carlo": args.monte_carlo}
    if args.k is not None:
        options["k"] = args.k
    return {"target": args.target, "sweep": sweep, "options": options}


def run(args: argparse.Namespace) -> int:
    if args.server is not None:  # a client of lrms serve: the standard library only
        from service.cli.measure_remote import run_remote

        return run_remote(args)
    from service.cli.measure_remote import REMOTE_ONLY

    given = [flag for attr, flag in REMOTE_ONLY if getattr(args, attr, None) is not None]
    if given:
        from service.errors import ServiceError

        raise ServiceError(f"only with --server: {', '.join(given)} (the embedded rig needs no token or time limit)")
    import os

    # one BLAS thread: the fits are then bit-for-bit repeatable (lrms replay), and the rig's
    # threads keep the cores
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    import json
    import shutil
    import sys
    import time

    # only the config and request models before the rig process starts: the rig code, the API
    # and the store load while it boots (service.isolated.isolated_service). The sweep, mapping
    # and fit run in the rig process (its fit worker imports the fit code), so this process
    # does not import them to settle its heap (Service.start's default for lrms serve)
    from service.config import load_config
    from service.errors import ServiceError
    from service.isolated import isolated_service
    from service.models import MeasurementRequest, resolve_sweep

    try:
        request = MeasurementRequest.model_validate(request_body(args))
    except ValueError as exc:
        raise ServiceError(f"bad measurement request: {exc}") from None
    cfg = load_config(args.config, storage_dir=args.data)
    resolve_sweep(request.sweep, cfg)  # against the rig's limits before it is opened (RequestFieldError)
    svc, rig = isolated_service(cfg)
    try:
        svc.start(settle_heap=False)
        m = svc.runner.submit(request)
        final = None
        while final is None:
            latest = svc.hub.latest(m.id)
            if latest is not None and not args.quiet:
                ev = latest[1]
                print(
                    progress_bar(float(ev.get("progress") or 0.0), str(ev.get("message") or ev["state"])),
                    end="",
                    file=sys.stderr,
                    flush=True,
                )
            current = svc.store.get(m.id)
            if current.state in ("done", "failed", "cancelled"):
                final = current
            else:
                time.sleep(0.1)
        if not args.quiet:
            print(file=sys.stderr)
    finally:
        svc.stop()
        rig.close()
    if final.raw_path and args.out:
        shutil.copyfile(final.raw_path, args.out)
    if final.cloud_path and args.cloud:
        shutil.copyfile(final.cloud_path, args.cloud)
    if final.state != "done" or final.result is None:
        raise ServiceError(f"measurement {final.state}: {final.error} (raw log: {final.raw_path})")
    result = dict(final.result)
    result["raw_path"] = final.raw_path
    result["cloud_path"] = final.cloud_path
    if args.plot:
        from service.plots import plot_measurement

        plot_measurement(final.cloud_path, result, cfg, args.plot)
    print(json.dumps(result, indent=2))
    return 0
