"""The dashboard's forms that start something, each sent once.

Revision ID: 0015
Revises: 0014
Create Date: 2026-12-06
"""

import sqlalchemy as sa
from alembic import op

revision = "0015"
down_revision = "0014"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "web_form_uses",
        sa.Column("form_key", sa.String(64), primary_key=True),
        sa.Column("used_at", sa.DateTime(), nullable=False, index=True),
    )


def downgrade() -> None:
    op.drop_table("web_form_uses")
