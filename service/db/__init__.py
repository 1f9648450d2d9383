"""The database behind the result store: tables (:mod:`service.db.schema`), engines for a storage URL
(:mod:`service.db.engine`) and Alembic migrations (:mod:`service.db.migrate`).

This module itself is light (no SQLAlchemy): the rig id rules, which the config checks.
"""

from __future__ import annotations

import re
import socket

#: The longest rig id (``[storage] rig_id``).
RIG_ID_LENGTH = 64
#: What a rig id may hold: letters, digits, ``.``, ``_`` and ``-`` (a host name fits).
RIG_ID_RE = re.compile(r"^[A-Za-z0-9._-]{1,64}$")


def default_rig_id() -> str:
    """This machine's host name (cut to the allowed characters and length), else ``"rig"``."""
    name = re.sub(r"[^A-Za-z0-9._-]", "-", socket.gethostname())[:RIG_ID_LENGTH].strip("-")
    return name or "rig"


def check_rig_id(rig_id: str) -> str:
    """``rig_id`` if it is a valid rig id, else :class:`ValueError` saying why."""
    if not RIG_ID_RE.fullmatch(rig_id):
        raise ValueError(
            f"rig id {rig_id!r}: 1 to {RIG_ID_LENGTH} letters, digits, '.', '_' or '-' (it tags every stored row)"
        )
    return rig_id
