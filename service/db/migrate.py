"""Alembic migrations of the result store, run at the store's start-up and by ``lrms db upgrade``.

The scripts live in ``service/db/migrations`` (no ``alembic.ini``: the configuration is built here).
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import Engine

MIGRATIONS = Path(__file__).parent / "migrations"


def alembic_config(engine: Engine, rig_id: str) -> Config:
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS))
    cfg.attributes["engine"] = engine
    cfg.attributes["rig_id"] = rig_id
    return cfg


@cache
def head() -> str:
    """The newest revision of the scripts."""
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS))
    rev = ScriptDirectory.from_config(cfg).get_current_head()
    assert rev is not None
    return rev


def current(engine: Engine) -> str | None:
    """The revision the database is at (None: never migrated, a new or a pre-migrations database)."""
    with engine.connect() as conn:
        return MigrationContext.configure(conn).get_current_revision()


def upgrade(engine: Engine, rig_id: str, revision: str = "head") -> str | None:
    """Bring the database to ``revision``; rows that get a rig id in the process get ``rig_id``.
    Returns the revision it is at."""
    if revision == "head" and current(engine) == head():
        return head()
    command.upgrade(alembic_config(engine, rig_id), revision)
    return current(engine)
