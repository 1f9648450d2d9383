"""Alembic migrations of the result store, run at the store's start-up and by ``lrms db upgrade``.

The scripts live in ``service/db/migrations`` (no ``alembic.ini``: the configuration is built here).
Alembic (a third of a second of imports) loads only when a migration runs or the scripts are read:
a store already at :data:`HEAD` is recognised by one query of its ``alembic_version`` table.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING

from sqlalchemy import Engine, inspect, text

if TYPE_CHECKING:
    from alembic.config import Config

MIGRATIONS = Path(__file__).parent / "migrations"

#: The newest revision of the scripts, as :func:`head` reads it from them (a test holds the two
#: equal: set it with each new script). A store at it needs no migration and loads no Alembic.
HEAD = "0005"


def alembic_config(engine: Engine, rig_id: str) -> Config:
    from alembic.config import Config

    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS))
    cfg.attributes["engine"] = engine
    cfg.attributes["rig_id"] = rig_id
    return cfg


@cache
def head() -> str:
    """The newest revision of the scripts (read by Alembic)."""
    from alembic.config import Config
    from alembic.script import ScriptDirectory

    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS))
    rev = ScriptDirectory.from_config(cfg).get_current_head()
    assert rev is not None
    return rev


def current(engine: Engine) -> str | None:
    """The revision the database is at (None: never migrated, a new or a pre-migrations database)."""
    with engine.connect() as conn:
        if not inspect(conn).has_table("alembic_version"):
            return None
        revs = list(conn.execute(text("SELECT version_num FROM alembic_version")).scalars())
        if len(revs) <= 1:
            return revs[0] if revs else None
        from alembic.runtime.migration import MigrationContext

        return MigrationContext.configure(conn).get_current_revision()  # several heads: Alembic says why not


def upgrade(engine: Engine, rig_id: str, revision: str = "head") -> str | None:
    """Bring the database to ``revision``; rows that get a rig id in the process get ``rig_id``.
    Returns the revision it is at."""
    if revision == "head" and current(engine) == HEAD:
        return HEAD
    from alembic import command

    command.upgrade(alembic_config(engine, rig_id), revision)
    return current(engine)
