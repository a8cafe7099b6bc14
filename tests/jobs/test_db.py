"""SQLite under several writers: a transaction that reads in a savepoint before it writes
is not refused because another connection committed in between. A database out of reach
is waited out."""

from __future__ import annotations

import threading

import pytest
from sqlalchemy import create_engine, text
from sqlalchemy.exc import IntegrityError

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


def test_a_call_that_fails_for_another_reason_is_not_tried_again(tmp_path) -> None:
    engine = create_engine(f"sqlite:///{tmp_path}/dncq.db")
    tries: list[int] = []

    def wrong() -> None:
        tries.append(1)
        with engine.begin() as connection:
            connection.execute(text("CREATE TABLE IF NOT EXISTS t (x INTEGER PRIMARY KEY)"))
            connection.execute(text("INSERT INTO t VALUES (1), (1)"))

    with pytest.raises(IntegrityError):
        db.when_reachable(wrong, wait_s=30, on_wait=lambda _: None)
    assert len(tries) == 1
