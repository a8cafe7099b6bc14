"""Wrong API keys from one address sent at the same moment, to one API process or several:
each counts, and one that meets the lock-out another began is refused as locked without
beginning it again (on PostgreSQL and on SQLite)."""

from __future__ import annotations

from datetime import timedelta
from typing import Any

import pytest
from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from jobs import db
from jobs.auth import wrong_keys
from jobs.auth.models import WrongKeyCount
from jobs.models import utcnow
from jobs.settings import Settings
from tests.jobs.helpers import while_another_writes

ADDRESS = "10.0.0.7"


@pytest.fixture
def on_database(settings: Settings, database_url: str) -> Settings:
    """The test's dncq on each database, no wrong key counted yet (the PostgreSQL database
    is the module's)."""
    with db.session_scope(database_url) as session:
        session.execute(delete(WrongKeyCount))
    return settings.model_copy(update={"database_url": database_url})


def _counted(settings: Settings) -> WrongKeyCount:
    with db.session_scope(settings.resolved_database_url) as session:
        row = session.get_one(WrongKeyCount, ADDRESS)
        session.expunge(row)
        return row


def _sends_a_wrong_key(settings: Settings) -> Any:
    def count() -> wrong_keys.Counted:
        with db.session_scope(settings.resolved_database_url) as session:
            return wrong_keys.count_wrong_key(session=session, settings=settings,
                                              address=ADDRESS)
    return count


@pytest.mark.parametrize("counted_before", [False, True],
                         ids=["the first wrong keys", "wrong keys after others"])
def test_two_wrong_keys_at_once_both_count_towards_the_lock_out(
        on_database, counted_before) -> None:
    if counted_before:
        with db.session_scope(on_database.resolved_database_url) as session:
            session.add(WrongKeyCount(address=ADDRESS, failures=0))

    def counted_meanwhile(session: Session) -> None:  # what another wrong key writes
        session.merge(WrongKeyCount(address=ADDRESS, failures=1, failed_since=utcnow()))
        session.flush()

    other = while_another_writes(on_database.resolved_database_url, counted_meanwhile,
                                 _sends_a_wrong_key(on_database))

    assert other.get("result") == wrong_keys.Counted(None)
    assert _counted(on_database).failures == 2  # not 1: a guess at once is no free guess


def test_a_wrong_key_that_meets_the_lock_out_is_refused_as_locked_without_locking_again(
        on_database) -> None:
    until = utcnow() + timedelta(seconds=on_database.signin_lockout_s)

    def locked_meanwhile(session: Session) -> None:  # what the key that locks it writes
        session.merge(WrongKeyCount(address=ADDRESS, failures=0, locked_until=until))
        session.flush()

    other = while_another_writes(on_database.resolved_database_url, locked_meanwhile,
                                 _sends_a_wrong_key(on_database))

    # Not `locked_now`: the lock-out is written to the audit trail by the key that began it.
    assert other.get("result") == wrong_keys.Counted(until)
    assert (_counted(on_database).failures, _counted(on_database).locked_until) == (0, until)


def test_the_counts_of_addresses_whose_window_and_lock_out_ended_are_forgotten(
        on_database) -> None:
    """Else every address a guesser ever sent from (IPv6 has /64s to spare) kept a row."""
    now, window = utcnow(), timedelta(seconds=on_database.signin_window_s)
    with db.session_scope(on_database.resolved_database_url) as session:
        session.add_all([
            WrongKeyCount(address="10.0.1.1", failures=2, failed_since=now - 2 * window),
            WrongKeyCount(address="10.0.1.2", failures=0, locked_until=now - window / 10),
            WrongKeyCount(address="10.0.1.3", failures=2, failed_since=now - window / 2),
            WrongKeyCount(address="10.0.1.4", failures=0, locked_until=now + window),
            WrongKeyCount(address="10.0.1.5", failures=0)])  # another count's, just made

    with db.session_scope(on_database.resolved_database_url) as session:
        wrong_keys.count_wrong_key(session=session, settings=on_database, address=ADDRESS)
    with db.session_scope(on_database.resolved_database_url) as session:
        kept = sorted(session.scalars(select(WrongKeyCount.address)))

    assert kept == [ADDRESS, "10.0.1.3", "10.0.1.4", "10.0.1.5"]
    assert _counted(on_database).failures == 1


def test_the_failures_that_locked_an_address_out_are_kept_and_paid_for_when_it_ends(
        on_database) -> None:
    short = on_database.model_copy(update={"signin_lockout_s": 60.0})
    count = _sends_a_wrong_key(short)
    for _ in range(short.signin_max_failures):
        last = count()
    locked = _counted(short)
    assert last.locked_now and locked.failures == short.signin_max_failures
    assert locked.failed_since is not None  # shown to the admin: what locked it, since when

    with db.session_scope(short.resolved_database_url) as session:  # the lock-out ended,
        row = session.get_one(WrongKeyCount, ADDRESS)  # its window not
        row.locked_until = utcnow() - timedelta(seconds=1)
    after = count()

    assert after.locked_until is None and _counted(short).failures == 1
