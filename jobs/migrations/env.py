"""Alembic environment: runs dncq's migrations on the engine handed over by jobs.db."""

import contextlib
from collections.abc import Iterator

from alembic import context
from sqlalchemy import Connection, create_engine

import jobs.auth.models  # noqa: F401  (their tables in the metadata)
import jobs.backup_models  # noqa: F401
import jobs.inbox.models  # noqa: F401
import jobs.library.models  # noqa: F401
import jobs.web.models  # noqa: F401
from jobs.models import Base

config = context.config
target_metadata = Base.metadata


@contextlib.contextmanager
def foreign_keys_off(connection: Connection) -> Iterator[None]:
    """SQLite's foreign keys off while the migrations run, as Alembic's batch mode needs: it
    drops a table to put its copy in its place, and the drop deleted the rows of every table
    below it (ON DELETE CASCADE). The pragma does nothing inside a transaction: set around
    the migrations' own, and back on before the connection returns to the pool."""
    if connection.dialect.name != "sqlite":
        yield
        return
    was_on = connection.exec_driver_sql("PRAGMA foreign_keys").scalar()
    connection.exec_driver_sql("PRAGMA foreign_keys=OFF")
    connection.commit()
    try:
        yield
    finally:
        connection.rollback()  # a failed migration's transaction, if Alembic left one open
        connection.exec_driver_sql(f"PRAGMA foreign_keys={'ON' if was_on else 'OFF'}")
        connection.commit()


engine = config.attributes.get("engine") or create_engine(
    config.get_main_option("sqlalchemy.url") or "sqlite://")
with engine.connect() as connection, foreign_keys_off(connection):
    context.configure(
        connection=connection,
        target_metadata=target_metadata,
        render_as_batch=connection.dialect.name == "sqlite",  # SQLite alters tables by copy
    )
    with context.begin_transaction():
        context.run_migrations()
