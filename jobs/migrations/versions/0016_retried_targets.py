"""A target retried on request counts its tries from the retry.

Revision ID: 0016
Revises: 0015
Create Date: 2026-12-06
"""

import sqlalchemy as sa
from alembic import op

revision = "0016"
down_revision = "0015"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("targets") as table:
        table.add_column(sa.Column("retried_after", sa.Integer(), nullable=True))
        table.add_column(sa.Column("retried_at", sa.DateTime(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("targets") as table:
        table.drop_column("retried_at")
        table.drop_column("retried_after")
