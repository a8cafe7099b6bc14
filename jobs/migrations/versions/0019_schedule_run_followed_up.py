"""A schedule's run records when its backup's retention pass and alert were done, so that an
assembly delivered again after a lost worker does them if they were not, and only then.

Revision ID: 0019
Revises: 0018
Create Date: 2026-12-06
"""

import sqlalchemy as sa
from alembic import op

revision = "0019"
down_revision = "0018"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("schedule_runs") as table:
        table.add_column(sa.Column("followed_up_at", sa.DateTime(), nullable=True))
    # A run whose backup is registered had them done then; one still running has them owed.
    op.execute("UPDATE schedule_runs SET followed_up_at = created_at WHERE job_id IN "
               "(SELECT job_id FROM backups WHERE job_id IS NOT NULL)")


def downgrade() -> None:
    with op.batch_alter_table("schedule_runs") as table:
        table.drop_column("followed_up_at")
