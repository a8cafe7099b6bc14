"""The failed sign-ins of the admin key's `admin` (a name no user has), counted and locked
out as a user's are.

Revision ID: 0020
Revises: 0019
Create Date: 2026-12-08
"""

import sqlalchemy as sa
from alembic import op

revision = "0020"
down_revision = "0019"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "signin_counts",
        sa.Column("name", sa.String(64), primary_key=True),
        sa.Column("failed_signins", sa.Integer(), nullable=False),
        sa.Column("failed_since", sa.DateTime(), nullable=True),
        sa.Column("locked_until", sa.DateTime(), nullable=True),
    )


def downgrade() -> None:
    op.drop_table("signin_counts")
