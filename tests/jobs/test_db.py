"""SQLite under several writers: a transaction that reads in a savepoint before it writes
is not refused because another connection committed in between. A database out of reach
is waited out."""

from __future__ import annotations

import socket
import threading
from collections.abc import Iterator

import pytest
from sqlalchemy import create_engine, text
from sqlalchemy.exc import IntegrityError, OperationalError

from jobs import db

INSERT = text("INSERT INTO library_programs (folder, name, deleted, created_at) "
              "VALUES (:folder, :name, 0, '2026-12-02')")


def _interleaved(url: str, *, write_first: bool) -> str | None:
    """A reads in a savepoint, B commits a write meanwhile, then A writes; A's error."""
    factory = db.session_factory(url)
    a, b = factory(), factory()
    b_done = threading.Event()

    def other_writer() -> None:
        b.execute(INSERT, {"folder": "B", "name": "1"})
        b.commit()
        b_done.set()

    try:
        if write_first:
            db.write_first(a)
        with a.begin_nested():
            a.execute(text("SELECT count(*) FROM library_programs")).all()
            writer = threading.Thread(target=other_writer)
            writer.start()
            # Without the lock B commits now, however slow the host; with it B waits for A.
            b_done.wait(0.5 if write_first else 30)
            a.execute(INSERT, {"folder": "A", "name": "1"})
        a.commit()
        writer.join(10)
        return None
    except Exception as exc:
        return str(exc).splitlines()[0]
    finally:
        a.close()
        b.close()


def test_a_savepoint_that_reads_then_writes_is_refused_without_the_lock_taken_first(
        tmp_path) -> None:
    url = f"sqlite:///{tmp_path / 'a.db'}"
    db.upgrade(url)

    assert "database is locked" in (_interleaved(url, write_first=False) or "")


def test_with_the_write_lock_taken_first_both_writers_land(tmp_path) -> None:
    url = f"sqlite:///{tmp_path / 'b.db'}"
    db.upgrade(url)

    assert _interleaved(url, write_first=True) is None
    with db.session_scope(url) as session:
        rows = session.execute(text("SELECT folder FROM library_programs ORDER BY folder"))
        assert [r[0] for r in rows] == ["A", "B"]


def test_a_call_waits_out_a_database_it_cannot_reach_and_says_so_once(
        tmp_path, monkeypatch) -> None:
    monkeypatch.setattr(db, "RETRY_UNREACHABLE_S", 0.01)
    folder = tmp_path / "mounted-later"
    engine = create_engine(f"sqlite:///{folder}/dncq.db")
    tries: list[int] = []
    said: list[BaseException] = []

    def one() -> int:
        tries.append(1)
        if len(tries) == 4:
            folder.mkdir()  # the database comes back
        with engine.connect() as connection:
            return int(connection.execute(text("SELECT 1")).scalar_one())

    assert db.when_reachable(one, wait_s=30, on_wait=said.append) == 1
    assert len(tries) == 4
    assert len(said) == 1  # three misses, one warning


@pytest.mark.parametrize(("statement", "error"), [
    ("INSERT INTO t VALUES (1), (1)", IntegrityError),
    ("SELECT * FROM no_such_table", OperationalError),  # SQLite's class of a lock timeout too
])
def test_a_call_that_fails_for_another_reason_is_not_tried_again(
        tmp_path, statement: str, error: type[Exception]) -> None:
    engine = create_engine(f"sqlite:///{tmp_path}/dncq.db")
    tries: list[int] = []

    def wrong() -> None:
        tries.append(1)
        with engine.begin() as connection:
            connection.execute(text("CREATE TABLE IF NOT EXISTS t (x INTEGER PRIMARY KEY)"))
            connection.execute(text(statement))

    with pytest.raises(error):
        db.when_reachable(wrong, wait_s=30, on_wait=lambda _: None)
    assert len(tries) == 1


def test_a_sqlite_database_locked_past_its_timeout_is_out_of_reach(tmp_path) -> None:
    url = f"sqlite:///{tmp_path}/dncq.db"
    holder = create_engine(url)
    waiter = create_engine(url, connect_args={"timeout": 0.1})
    with holder.connect() as held:
        held.exec_driver_sql("CREATE TABLE t (x INTEGER)")
        held.commit()
        held.exec_driver_sql("BEGIN IMMEDIATE")  # the write lock, held
        with pytest.raises(OperationalError) as refused, waiter.begin() as other:
            other.exec_driver_sql("INSERT INTO t VALUES (1)")
        held.rollback()

    assert "database is locked" in str(refused.value)
    assert db.unreachable(refused.value)


@pytest.fixture
def silent_server() -> Iterator[int]:
    """A port whose server takes connections and never says a word: a PostgreSQL host behind
    a firewall that drops its answers, or one hung, as libpq meets it."""
    with socket.create_server(("127.0.0.1", 0)) as server:
        yield server.getsockname()[1]


@pytest.mark.parametrize("query", ["", "?connect_timeout=2"])
def test_a_postgresql_that_never_answers_is_out_of_reach_after_the_connect_timeout(
        silent_server: int, monkeypatch, query: str) -> None:
    # The default timeout, or the URL's own (which the default does not replace).
    monkeypatch.setattr(db, "CONNECT_TIMEOUT_S", 100 if query else 2)
    url = f"postgresql+psycopg://dncq@127.0.0.1:{silent_server}/dncq{query}"
    refused: list[BaseException] = []

    def connect() -> None:
        try:
            db.engine_for(url).connect().close()
        except Exception as exc:
            refused.append(exc)

    attempt = threading.Thread(target=connect, daemon=True)
    attempt.start()
    attempt.join(60)  # without a timeout, libpq waits for the server's answer for ever

    assert not attempt.is_alive(), "the connect still waits for the silent server"
    assert len(refused) == 1 and db.unreachable(refused[0])
