"""Alembic environment: runs dncq's migrations on the engine handed over by jobs.db."""

from alembic import context
from sqlalchemy import create_engine

import jobs.auth.models  # noqa: F401  (their tables in the metadata)
import jobs.inbox.models  # noqa: F401
import jobs.library.models  # noqa: F401
from jobs.models import Base

config = context.config
target_metadata = Base.metadata

engine = config.attributes.get("engine") or create_engine(
    config.get_main_option("sqlalchemy.url") or "sqlite://")
with engine.connect() as connection:
    context.configure(
        connection=connection,
        target_metadata=target_metadata,
        render_as_batch=connection.dialect.name == "sqlite",  # SQLite alters tables by copy
    )
    with context.begin_transaction():
        context.run_migrations()
