"""The tables of the result store, in one :data:`metadata` for SQLite and PostgreSQL.

The schema is what the migrations in ``service/db/migrations/versions`` build (a test compares the
two). A module that adds tables of its own (calibrations, recipes) adds them to :data:`metadata`
and a migration that creates them, and opens them on :attr:`service.store.Store.engine`.

Every row carries the ``rig_id`` of the service that made it, so many rigs (one ``lrms serve``
each) share one database. JSON documents (requests, results, templates) are stored as text, as the
first SQLite store did; times are epoch seconds; flags are integers 0/1.
"""

from __future__ import annotations

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    Column,
    Float,
    ForeignKey,
    Index,
    Integer,
    MetaData,
    String,
    Table,
    Text,
    UniqueConstraint,
)
from sqlalchemy.dialects.sqlite import REAL

from service.db import RIG_ID_LENGTH

#: Constraint and index names Alembic can find again on every backend.
NAMING = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}

metadata = MetaData(naming_convention=NAMING)

#: A double: ``REAL`` on SQLite (as the first store declared it), ``FLOAT`` (8 bytes) on PostgreSQL.
Double = Float().with_variant(REAL(), "sqlite")


measurements = Table(
    "measurements",
    metadata,
    Column("id", Text, primary_key=True),
    Column("seq", Integer, nullable=False),  # queue order; one sequence over all rigs
    Column("created_at", Double, nullable=False),
    Column("started_at", Double),
    Column("finished_at", Double),
    Column("state", Text, nullable=False),
    Column("request", Text, nullable=False),
    Column("progress", Double, nullable=False, server_default="0"),
    Column("message", Text, nullable=False, server_default=""),
    Column("result", Text),
    Column("error", Text),
    Column("raw_path", Text),
    Column("cloud_path", Text),
    Column("schedule_id", Text),
    Column("raw_truncated", Integer, nullable=False, server_default="0"),
    Column("rig_id", String(RIG_ID_LENGTH), nullable=False),
    Index("measurements_state", "state", "seq"),
    Index("measurements_rig_state", "rig_id", "state", "seq"),
)

schedules = Table(
    "schedules",
    metadata,
    Column("id", Text, primary_key=True),
    Column("created_at", Double, nullable=False),
    Column("name", Text, nullable=False, server_default=""),
    Column("cron", Text),
    Column("interval_s", Double),
    Column("template", Text, nullable=False),
    Column("enabled", Integer, nullable=False, server_default="1"),
    Column("next_run", Double),
    Column("last_run", Double),
    Column("last_measurement_id", Text),
    Column("rig_id", String(RIG_ID_LENGTH), nullable=False),
    Index("schedules_rig", "rig_id", "created_at"),
)

store_version = Table(
    "store_version",
    metadata,
    Column("id", Integer, primary_key=True, autoincrement=False),
    Column("n", BigInteger, nullable=False),
)
"""One row (``id`` 1) whose counter every write transaction of the store increments first: readers
compare it to know when what they cached may be stale, and taking its row lock serialises the
store's writers on every backend (so ``seq`` = max + 1 is safe with many rigs writing at once)."""

calibrations = Table(
    "calibrations",
    metadata,
    Column("id", String(32), primary_key=True),
    Column("seq", Integer, nullable=False),
    Column("created", String(40), nullable=False),
    Column("name", String(200), nullable=False, default=""),
    Column("comment", Text, nullable=False, default=""),
    Column("rig_id", String(200), nullable=True),
    Column("result", Text, nullable=False),
    Column("active", Boolean, nullable=False, default=False),
    Index("calibrations_seq", "seq"),
    Index("calibrations_rig", "rig_id", "seq"),
)
"""Rig calibrations (:mod:`service.calstore`): the ``CalibrationResult`` JSON, at most one active per rig."""

recipes = Table(
    "recipes",
    metadata,
    Column("name", String(64), primary_key=True),
    Column("latest_version", Integer, nullable=False),
    Column("retired", Boolean, nullable=False, default=False),
    Column("created_at", Double, nullable=False),
    Column("retired_at", Double, nullable=True),
)
"""Part recipes (:mod:`service.recipestore`): one row per name, shared by every rig of the plant."""

recipe_versions = Table(
    "recipe_versions",
    metadata,
    Column("name", String(64), ForeignKey("recipes.name"), primary_key=True),
    Column("version", Integer, primary_key=True),
    Column("created_at", Double, nullable=False),
    Column("body", Text, nullable=False),
)
"""Every version of every recipe (a change is a new version; results name the one they used)."""

recipe_measurements = Table(
    "recipe_measurements",
    metadata,
    Column("measurement_id", String(64), primary_key=True),
    Column("recipe", String(64), nullable=False),
    Column("version", Integer, nullable=False),
    Column("part_id", String(128), nullable=False),
    Column("operator", String(200), nullable=True),
    Column("created_at", Double, nullable=False),
    Index("recipe_measurements_by_recipe", "recipe", "created_at"),
)
"""A part's measurement -> its recipe, version, part id and operator (the recipe's history)."""

result_versions = Table(
    "result_versions",
    metadata,
    Column("id", Integer, primary_key=True, autoincrement=True),
    Column("measurement_id", String(64), nullable=False),
    Column("version", Integer, nullable=False),
    Column("created_at", Double, nullable=False),
    Column("software_version", String(64), nullable=False),
    Column("calibration_id", String(64), nullable=False),
    Column("raw_sha256", String(64), nullable=False),
    Column("result", JSON, nullable=False),
    Index("result_versions_measurement", "measurement_id"),
    UniqueConstraint("measurement_id", "version", name="result_versions_number"),
    UniqueConstraint(
        "measurement_id", "raw_sha256", "calibration_id", "software_version", name="result_versions_inputs"
    ),
)
"""Re-evaluations of archived raw logs (:mod:`service.versionstore`, ``lrms reprocess``); the original
result stays in ``measurements``."""

reprocess_calibrations = Table(
    "reprocess_calibrations",
    metadata,
    Column("id", String(64), primary_key=True),
    Column("created_at", Double, nullable=False),
    Column("source", String(1024), nullable=False, default=""),
    Column("calibration", JSON, nullable=False),
)
"""Calibration files given to ``lrms reprocess``, kept under their content hash."""
