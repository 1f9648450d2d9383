"""``lrms db upgrade``: bring the result database of a rig configuration to the newest schema.

``lrms serve`` does the same at start-up; this command lets an operator migrate a shared database
(``[storage] url``) once, before the services of the rigs start, and see the revision it is at.
"""

from __future__ import annotations

import argparse

HELP = "migrate the result database ([storage] url, else the SQLite file in [storage] dir) to the newest schema"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="RIG.toml", help="rig configuration (default: the simulated seed 003 rig)")
    parser.add_argument("--data", metavar="DIR", help="storage folder (overrides [storage] dir)")
    parser.add_argument("--url", help="database URL (overrides [storage] url)")


def run(args: argparse.Namespace) -> int:
    from sqlalchemy.exc import SQLAlchemyError

    from service.config import load_config
    from service.db import engine as db_engine
    from service.db import migrate
    from service.store import StoreError

    cfg = load_config(args.config, storage_dir=args.data)
    url = args.url or cfg.storage.db_url
    try:
        engine = db_engine.create(url)
    except db_engine.DatabaseError as exc:
        raise StoreError(str(exc)) from None
    try:
        before = migrate.current(engine)
        after = migrate.upgrade(engine, cfg.storage.rig_id)
    except (SQLAlchemyError, OSError) as exc:
        raise StoreError(f"cannot migrate {db_engine.shown(url)}: {exc}") from None
    finally:
        engine.dispose()
    print(f"lrms db: {db_engine.shown(url)} at revision {after} (was {before or 'none'}); rig id {cfg.storage.rig_id}")
    return 0
