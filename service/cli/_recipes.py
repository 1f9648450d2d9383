"""What ``lrms recipe import`` and ``lrms recipe export`` share: the rig's recipe store, opened from its config."""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from service.recipestore import RecipeStore


def add_store_arguments(parser: argparse.ArgumentParser) -> None:
    """The options that choose the database: ``--config`` and ``--data``."""
    parser.add_argument("--config", metavar="RIG.toml", help="rig configuration (default: the simulated seed 003 rig)")
    parser.add_argument("--data", metavar="DIR", help="storage folder (overrides [storage] dir)")


@contextmanager
def recipe_store(args: argparse.Namespace) -> Iterator[RecipeStore]:
    """The recipe store of the result database ``args`` name (opened and migrated), closed on exit."""
    from service.config import load_config
    from service.recipestore import RecipeStore
    from service.store import Store

    cfg = load_config(args.config, storage_dir=args.data)
    db = Store(cfg.storage.db_url, cfg.storage.rig_id)
    store = RecipeStore(db.engine)
    try:
        yield store
    finally:
        store.close()
        db.close()
