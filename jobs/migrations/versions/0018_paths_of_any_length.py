"""Paths of any length: a backed-up file under folders nested past 1200 characters, a
machine's root or a schedule's folder past 500, were refused by PostgreSQL.

Revision ID: 0018
Revises: 0017
Create Date: 2026-12-06
"""

import sqlalchemy as sa
from alembic import op

revision = "0018"
down_revision = "0017"
branch_labels = None
depends_on = None

# Each table's columns made Text, with their lengths before.
WIDENED = {"backup_files": {"path": 1200, "archive_path": 2000}, "machines": {"root": 500},
           "schedules": {"dir_at_cnc": 500}}


def upgrade() -> None:
    for table_name, columns in WIDENED.items():
        with op.batch_alter_table(table_name) as table:  # one copy of each on SQLite
            for column, length in columns.items():
                table.alter_column(column, type_=sa.Text(), existing_type=sa.String(length))


def downgrade() -> None:
    # PostgreSQL refuses the downgrade while a longer path is kept: none is cut.
    for table_name, columns in WIDENED.items():
        with op.batch_alter_table(table_name) as table:
            for column, length in columns.items():
                table.alter_column(column, type_=sa.String(length), existing_type=sa.Text())
