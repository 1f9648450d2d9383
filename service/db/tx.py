"""The write transaction of the tables that live beside the store's (calibrations, recipes, result
versions): the same one write lock as :class:`service.store.Store`'s own writes.

On SQLite, a transaction that is not marked :data:`service.db.engine.WRITE` is no transaction at
all (the engine runs reads in autocommit): two statements of one change would each commit alone.
:func:`write_transaction` marks it (``BEGIN IMMEDIATE``) and first increments the one row of
``store_version``, which on PostgreSQL holds that row's lock until the commit. Writers of every rig
and every table are thus serialised, so "read the largest number, insert the next one" and
"deactivate the others, activate this one" stay true until they commit, on both backends; and
readers that cache under :attr:`service.store.Store.version` see the change.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from sqlalchemy import Connection, Engine, update

from service.db.engine import WRITE
from service.db.schema import store_version

_BUMP = update(store_version).where(store_version.c.id == 1).values(n=store_version.c.n + 1)


@contextmanager
def write_transaction(engine: Engine) -> Iterator[Connection]:
    """A connection in a write transaction holding the database's write lock (committed at the end
    of the block, rolled back if it raises)."""
    with engine.connect() as conn:
        conn.execution_options(**{WRITE: True})
        with conn.begin():
            conn.execute(_BUMP)
            yield conn
