"""``lrms reprocess``: re-fit archived raw logs on Dask and store the results as new versions."""

from __future__ import annotations

import argparse

HELP = "re-fit archived raw logs on a Dask cluster; results become new result versions"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="RIG.toml", help="rig configuration (its [storage]: the result store)")
    parser.add_argument("--data", metavar="DIR", help="storage folder (overrides [storage] dir)")
    parser.add_argument("--since", metavar="DATE", help="only measurements created since (ISO date, UTC)")
    parser.add_argument("--until", metavar="DATE", help="only measurements created before (ISO date, UTC)")
    parser.add_argument("--rig", metavar="RIG_ID", help="only measurements of this rig (its [storage] rig_id)")
    parser.add_argument("--recipe", metavar="NAME", help="only measurements of this recipe")
    parser.add_argument(
        "--calibration",
        metavar="FILE_OR_ID",
        help="a rig calibration (lrms calibrate --out), or the id of one of the service's calibration store"
        " or of one used before (a service calibration applies to its own rig's measurements)",
    )
    parser.add_argument("--scheduler", metavar="tcp://HOST:8786", help="an existing Dask cluster (default: local)")
    parser.add_argument(
        "--workers", type=int, default=2, metavar="N", help="local cluster: worker processes (0: no Dask, this process)"
    )
    parser.add_argument("--archive", metavar="DIR_OR_URL", help="where the raw logs are (a directory or fsspec URL)")
    parser.add_argument("--parquet", metavar="OUT", help="also write every result version to this Parquet file")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    import os

    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")  # one BLAS thread per task: repeatable fits, one core each
    import json
    import sys
    from contextlib import nullcontext
    from typing import Any

    from service import reprocess as rp
    from service.config import load_config
    from service.db import check_rig_id
    from service.versionstore import LOGGED_CALIBRATION, VersionStore

    if args.workers < 0:
        raise rp.ReprocessError("--workers must be 0 or more")
    cfg = load_config(args.config, storage_dir=args.data)
    if cfg.storage.url is None and not cfg.storage.db_path.exists():
        raise rp.ReprocessError(f"no result store at {cfg.storage.db_path}")
    rig = args.rig
    if rig is not None:
        try:
            check_rig_id(rig)
        except ValueError as exc:
            raise rp.ReprocessError(f"--rig: {exc}") from None
    since = rp.parse_since(args.since) if args.since else None
    until = rp.parse_since(args.until, "--until") if args.until else None
    if since is not None and until is not None and until <= since:
        raise rp.ReprocessError(f"--until {args.until} is not after --since {args.since}: nothing to select")
    engine = rp.result_engine(cfg)
    try:
        store = VersionStore(engine)
        cal_id, kinematics = LOGGED_CALIBRATION, None
        if args.calibration:
            chosen = rp.resolve_calibration(args.calibration, store)
            cal_id, kinematics = chosen.id, chosen.kinematics
            if chosen.rig_id is not None:  # a rig's calibration: that rig's measurements only
                if rig is not None and rig != chosen.rig_id:
                    raise rp.ReprocessError(
                        f"calibration {chosen.id} belongs to rig {chosen.rig_id!r}, not to --rig {rig!r}"
                    )
                rig = chosen.rig_id
        measurements = rp.archived_measurements(engine, since, args.recipe, until=until, rig=rig)
    except BaseException:
        engine.dispose()
        raise
    local = args.scheduler is None and args.workers == 0
    ctx: Any = nullcontext(None) if local else rp.dask_client(args.scheduler, args.workers)
    with ctx as client:
        executor = rp.serial_executor if client is None else rp.dask_executor(client)
        summary = rp.reprocess(
            store,
            measurements,
            executor,
            archive=args.archive,
            calibration_id=cal_id,
            kinematics=kinematics,
            progress=None if args.quiet else rp.progress_bar(sys.stderr),
        )
    out = {**summary.to_dict(), "rig": rig}
    if args.parquet:
        out["parquet_rows"] = rp.write_parquet(args.parquet, store, measurements)
    engine.dispose()
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        print(summary.text() + (f"\n(measurements of rig {rig} only)" if rig is not None else ""))
        if args.parquet:
            print(f"{out['parquet_rows']} result versions written to {args.parquet}")
    return 2 if summary.failed else 0
