"""``lrms recipe export``: a stored recipe as TOML (the latest version, or one named)."""

from __future__ import annotations

import argparse

HELP = "write a stored recipe as TOML (to FILE, or to stdout)"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("name", help="recipe name")
    parser.add_argument("file", metavar="FILE.toml", nargs="?", help="where to write it (default: stdout)")
    parser.add_argument("--version", type=int, metavar="N", help="this version (default: the latest)")
    parser.add_argument("--config", metavar="RIG.toml", help="rig configuration (default: the simulated seed 003 rig)")
    parser.add_argument("--data", metavar="DIR", help="storage folder (overrides [storage] dir)")


def run(args: argparse.Namespace) -> int:
    import sys
    from pathlib import Path

    from service.config import load_config
    from service.recipes import to_toml
    from service.recipestore import RecipeStore
    from service.store import Store

    cfg = load_config(args.config, storage_dir=args.data)
    db = Store(cfg.storage.db_url, cfg.storage.rig_id)  # opens (and migrates) the result database
    store = RecipeStore(db.engine)
    try:
        r = store.latest(args.name) if args.version is None else store.version(args.name, args.version)
    finally:
        store.close()
        db.close()
    text = to_toml(r, r.version)
    if args.file is None:
        sys.stdout.write(text)
    else:
        Path(args.file).write_text(text, encoding="utf-8")
        print(f"{r.name} version {r.version} -> {args.file}", file=sys.stderr)
    return 0
