"""Every row tagged with its rig; the store's version row.

``measurements.rig_id`` and ``schedules.rig_id`` (not null): the rows already there get the rig id
of the service that runs the upgrade (``config.attributes["rig_id"]``: they were made by the one
rig that used the file). Indexes for the per-rig queue and schedule list, and ``store_version``,
the counter every write increments (see :mod:`service.db.schema`).

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-24
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import context, op

revision = "0002"
down_revision: str | None = "0001"
branch_labels: str | None = None
depends_on: str | None = None

RIG_ID_LENGTH = 64


def upgrade() -> None:
    rig = str(context.config.attributes.get("rig_id") or "rig")
    sqlite = op.get_bind().dialect.name == "sqlite"
    for table in ("measurements", "schedules"):
        op.add_column(table, sa.Column("rig_id", sa.String(RIG_ID_LENGTH), nullable=False, server_default=rig))
        # the default only filled the rows there; a new row names its rig itself
        if sqlite:  # SQLite cannot drop a column default in place: the table is copied
            with op.batch_alter_table(table, recreate="always") as batch:
                batch.alter_column("rig_id", server_default=None, existing_type=sa.String(RIG_ID_LENGTH))
                # the first store's "id TEXT PRIMARY KEY" let SQLite take NULL ids (it never wrote one)
                batch.alter_column("id", nullable=False, existing_type=sa.Text)
        else:
            op.alter_column(table, "rig_id", server_default=None, existing_type=sa.String(RIG_ID_LENGTH))
    op.create_index("measurements_rig_state", "measurements", ["rig_id", "state", "seq"])
    op.create_index("schedules_rig", "schedules", ["rig_id", "created_at"])
    version = op.create_table(
        "store_version",
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=False),
        sa.Column("n", sa.BigInteger, nullable=False),
    )
    op.bulk_insert(version, [{"id": 1, "n": 0}])


def downgrade() -> None:
    op.drop_table("store_version")
    op.drop_index("schedules_rig", "schedules")
    op.drop_index("measurements_rig_state", "measurements")
    for table in ("measurements", "schedules"):
        with op.batch_alter_table(table) as batch:
            batch.drop_column("rig_id")
