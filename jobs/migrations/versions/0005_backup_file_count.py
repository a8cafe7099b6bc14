"""Backups keep how many files they hold, so listing them counts no file rows.

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-26
"""

import sqlalchemy as sa
from alembic import op

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("backups") as batch:  # SQLite alters tables by copying them
        batch.add_column(sa.Column("file_count", sa.Integer(), nullable=False,
                                   server_default="0"))
    op.execute("UPDATE backups SET file_count = (SELECT count(*) FROM backup_files"
               " WHERE backup_files.backup_id = backups.id)")


def downgrade() -> None:
    with op.batch_alter_table("backups") as batch:
        batch.drop_column("file_count")
