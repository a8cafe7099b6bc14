"""Wrong API keys from one address sent at the same moment, to one API process or several:
each counts, and one that meets the lock-out another began is refused as locked without
beginning it again (on PostgreSQL and on SQLite)."""

from __future__ import annotations

from datetime import timedelta
from typing import Any

import pytest
from sqlalchemy import delete
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
