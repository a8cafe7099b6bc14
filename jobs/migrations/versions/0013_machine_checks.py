"""Each machine's last check, kept so that every process shows and counts the same.

Revision ID: 0013
Revises: 0012
Create Date: 2026-12-02
"""

import sqlalchemy as sa
from alembic import op

revision = "0013"
down_revision = "0012"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "machine_checks",
        sa.Column("machine_id", sa.String(64), primary_key=True),
        sa.Column("checked_at", sa.DateTime(), nullable=False),
        sa.Column("reachable", sa.Boolean(), nullable=False),
        sa.Column("found", sa.JSON(), nullable=False),
    )


def downgrade() -> None:
    op.drop_table("machine_checks")
