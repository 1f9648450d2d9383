"""Alembic's environment for the result store: run by :func:`service.db.migrate.upgrade` with the
store's engine (``config.attributes["engine"]``) and rig id (``config.attributes["rig_id"]``).

All pending migrations run in one transaction, taken as a write lock: ``BEGIN IMMEDIATE`` on SQLite,
a session advisory lock on PostgreSQL (DDL is transactional on both). Services starting at once
against one database thus migrate it once; the others wait, then find it at the head revision.
"""

from __future__ import annotations

from alembic import context
from sqlalchemy import Engine, text

from service.db.engine import WRITE
from service.db.schema import metadata

#: pg_advisory_lock key of the migrations (any constant the application uses for nothing else).
PG_LOCK_KEY = 0x6C726D73  # "lrms"


def run() -> None:
    engine = context.config.attributes["engine"]
    assert isinstance(engine, Engine)
    with engine.connect() as conn:
        pg = conn.dialect.name == "postgresql"
        if pg:
            conn.execute(text("SELECT pg_advisory_lock(:k)"), {"k": PG_LOCK_KEY})
            conn.commit()
        try:
            conn.execution_options(**{WRITE: True})
            context.configure(connection=conn, target_metadata=metadata, transactional_ddl=True)
            with context.begin_transaction():
                context.run_migrations()
        finally:
            if pg:
                conn.rollback()
                conn.execute(text("SELECT pg_advisory_unlock(:k)"), {"k": PG_LOCK_KEY})
                conn.commit()


if context.is_offline_mode():
    raise RuntimeError("the result store's migrations run online only (lrms db upgrade)")
run()
