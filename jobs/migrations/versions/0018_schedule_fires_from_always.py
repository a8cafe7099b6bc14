"""Every schedule says from when its fire times count: from its creation, unless it was
enabled again or given other times since.

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


def upgrade() -> None:
    op.execute("UPDATE schedules SET fires_from = created_at WHERE fires_from IS NULL")
    with op.batch_alter_table("schedules") as table:
        table.alter_column("fires_from", existing_type=sa.DateTime(), nullable=False)


def downgrade() -> None:
    with op.batch_alter_table("schedules") as table:
        table.alter_column("fires_from", existing_type=sa.DateTime(), nullable=True)
