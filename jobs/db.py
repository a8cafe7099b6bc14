"""Database engine and sessions; the schema is made and upgraded by Alembic migrations."""

from __future__ import annotations

import contextlib
import os
import sqlite3
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path
from typing import Any, TypeVar, cast

from alembic import command
from alembic.config import Config
from sqlalchemy import (
    CursorResult,
    Engine,
    Result,
    Select,
    Table,
    create_engine,
    event,
    insert,
    text,
)
from sqlalchemy import exc as sa_errors
from sqlalchemy.dialects.postgresql import insert as postgresql_insert
from sqlalchemy.dialects.sqlite import insert as sqlite_insert
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, sessionmaker

MIGRATIONS = Path(__file__).parent / "migrations"
T = TypeVar("T")
SelectT = TypeVar("SelectT", bound=Select)  # type: ignore[type-arg]
IN_CHUNK = 10_000  # ids per IN list: PostgreSQL takes at most 65,535 parameters a statement


def in_chunks(items: list[T]) -> Iterator[list[T]]:
    """`items` IN_CHUNK at a time: what one statement's IN list or rows may hold."""
    for start in range(0, len(items), IN_CHUNK):
        yield items[start:start + IN_CHUNK]


def _sqlite_pragmas(dbapi_conn, _record) -> None:  # type: ignore[no-untyped-def]
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA journal_mode=WAL")  # readers do not block the one writer
    cur.execute("PRAGMA busy_timeout=30000")  # ms a writer waits for another
    cur.execute("PRAGMA foreign_keys=ON")
    cur.execute("PRAGMA synchronous=NORMAL")
    cur.close()


@lru_cache(maxsize=8)
def engine_for(url: str) -> Engine:
    """One engine per database URL per process."""
    _urls_seen.add(url)
    if url.startswith("sqlite"):
        _private_sqlite_file(Path(url.removeprefix("sqlite:///")))
        engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 30})
        event.listen(engine, "connect", _sqlite_pragmas)
        return engine
    # Pre-ping: a connection the server cut (a restart, a failover) is replaced at checkout
    # instead of failing the request that drew it. One round trip per checkout; the runners
    # share their transactions (jobs.run.group_commit): about one checkout per three targets;
    # the API checks out one per request, and a request waiting for a machine one per poll.
    return create_engine(url, pool_size=20, max_overflow=50, pool_recycle=300,
                         pool_pre_ping=True, connect_args=_connect_args(url))


CONNECT_TIMEOUT_S = 10  # libpq's connect_timeout, unless the URL sets its own


def _connect_args(url: str) -> dict[str, Any]:
    """A bounded connect on PostgreSQL: libpq waits for a host that drops the packets as long
    as the kernel retries (two minutes), and every wait for the database (`when_reachable`)
    with it."""
    parsed = make_url(url)
    if parsed.get_backend_name() != "postgresql" or "connect_timeout" in parsed.query:
        return {}
    return {"connect_timeout": CONNECT_TIMEOUT_S}


def _private_sqlite_file(path: Path) -> None:
    """Create the database file 0600 before SQLite does: its -wal and -shm take its mode."""
    if str(path) in ("", ":memory:"):
        return
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    with contextlib.suppress(FileExistsError):
        os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))


def insert_rows(session: Session, table: Table, rows: list[dict[str, Any]]) -> None:
    """`session.execute(insert(table), rows)`, by COPY on PostgreSQL; in the session's
    transaction either way.

    A key a row lacks is NULL, not its column's default: name every column whose default
    is not NULL. COPY takes 1000 backup file rows in 2.4 ms, against 14 ms for one INSERT
    over an array per column and more for SQLAlchemy's multi-row INSERT, whose Python per
    row is most of it.
    """
    if not rows:
        return
    names = list(dict.fromkeys(name for row in rows for name in row))
    dialect = session.get_bind().dialect
    if dialect.name != "postgresql":  # an executemany: every row with the same keys
        session.execute(insert(table), [
            row if len(row) == len(names) else {name: row.get(name) for name in names}
            for row in rows])
        return
    from psycopg import sql  # PostgreSQL's driver, installed with dncq[postgres]

    # Each value as the column's type sends it: enums as their stored text, JSON wrapped.
    processors = [table.c[name].type.dialect_impl(dialect).bind_processor(dialect)
                  for name in names]
    statement = sql.SQL("COPY {} ({}) FROM STDIN").format(
        sql.Identifier(table.name), sql.SQL(", ").join(map(sql.Identifier, names)))
    driver = session.connection().connection.driver_connection
    assert driver is not None  # a connection the session holds is open
    with driver.cursor() as cursor, cursor.copy(statement) as copy:
        for row in rows:
            copy.write_row([
                None if (value := row.get(name, _ABSENT)) is _ABSENT
                else value if process is None else process(value)
                for name, process in zip(names, processors, strict=True)])


_ABSENT = object()  # a key a row of `insert_rows` lacks


def upsert_of(session: Session) -> Any:
    """The `insert` of the session's dialect, which has ON CONFLICT (PostgreSQL, SQLite)."""
    if session.get_bind().dialect.name == "postgresql":
        return postgresql_insert
    return sqlite_insert


def rowcount(result: Result[Any]) -> int:
    """Rows an UPDATE, DELETE or INSERT touched."""
    return int(cast(CursorResult[Any], result).rowcount)


def write_first(session: Session) -> None:
    """On SQLite, take the database's write lock now, before this transaction reads.

    A transaction that reads first (one a SAVEPOINT opens) and then writes, after another
    connection has committed, is refused at once with "database is locked" (WAL mode: its
    snapshot is stale); SQLite cannot wait that out. A transaction that starts by writing
    waits for the lock like any writer (busy_timeout). PostgreSQL needs nothing here.
    """
    if session.get_bind().dialect.name == "sqlite":
        # Any write statement takes the lock, even one that changes no row.
        session.execute(text("UPDATE alembic_version SET version_num = version_num WHERE 0"))


def held(session: Session, query: SelectT) -> SelectT:
    """`query` holding the rows it finds to the end of the transaction, read as another that
    held them left them (not from the session's own stale copies), the write lock taken
    first on SQLite (`write_first`): two that change one row at once take turns."""
    write_first(session)
    return query.with_for_update().execution_options(populate_existing=True)


def unreachable(exc: BaseException) -> bool:
    """Whether `exc` says the database could not be reached or answered in time (a restart,
    a failover, a full pool, SQLite's lock timeout), not that a statement was wrong."""
    if isinstance(exc, sa_errors.DBAPIError) and exc.connection_invalidated:
        return True
    if isinstance(exc, sa_errors.OperationalError) and \
            isinstance(exc.orig, sqlite3.OperationalError):
        # SQLite says a wrong statement (no such table) with the class of a lock timeout
        said = str(exc.orig).lower()
        return any(outage in said for outage in _SQLITE_OUTAGES)
    return isinstance(exc, (sa_errors.OperationalError, sa_errors.InterfaceError,
                            sa_errors.DisconnectionError, sa_errors.TimeoutError))


_SQLITE_OUTAGES = ("is locked", "unable to open", "disk i/o error")


RETRY_UNREACHABLE_S = 1.0  # how often a caller that found the database gone looks again


def when_reachable(call: Callable[[], T], *, wait_s: float,
                   on_wait: Callable[[BaseException], None]) -> T:
    """`call()`, tried again while the database is `unreachable`, for up to `wait_s` (and
    the try under way then); then what it raised. `on_wait` hears of the first miss only:
    an outage is said once, not once a second."""
    deadline = time.monotonic() + wait_s
    said = False
    while True:
        try:
            return call()
        except Exception as exc:
            if not unreachable(exc) or time.monotonic() >= deadline:
                raise
            if not said:
                on_wait(exc)
                said = True
            time.sleep(RETRY_UNREACHABLE_S)


def dispose_all() -> None:
    """Forget inherited pooled connections (in a forked child) without closing the parent's."""
    for engine in _engines():
        engine.dispose(close=False)


def _engines() -> list[Engine]:
    # lru_cache keeps the engines; reach them through the cache's own wrapper.
    return [engine_for(url) for url in _urls_seen]


_urls_seen: set[str] = set()


@lru_cache(maxsize=8)
def session_factory(url: str) -> sessionmaker[Session]:
    """Session factory bound to the engine for `url`."""
    return sessionmaker(engine_for(url), expire_on_commit=False)


@contextmanager
def session_scope(url: str) -> Iterator[Session]:
    """A session that commits on success and rolls back on error."""
    session = session_factory(url)()
    try:
        yield session
        session.commit()
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()


def alembic_config(url: str) -> Config:
    """Alembic configuration pointing at dncq's migrations and `url`."""
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS))
    cfg.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    cfg.attributes["engine"] = engine_for(url)
    return cfg


def upgrade(url: str) -> None:
    """Bring the schema at `url` to the newest migration, keeping its data."""
    command.upgrade(alembic_config(url), "head")
