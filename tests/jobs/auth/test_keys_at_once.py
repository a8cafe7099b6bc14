"""A named key revoked while it is used, or by two admins at once: it stays revoked from
the first revoke on, and is refused after it (on PostgreSQL and on SQLite)."""

from __future__ import annotations

from datetime import datetime

import pytest
from sqlalchemy import select
from sqlalchemy.orm import Session

from jobs import db
from jobs.auth import service
from jobs.auth.models import ApiKey, User
from jobs.auth.roles import Role
from jobs.settings import Settings
from tests.jobs.helpers import while_another_writes


@pytest.fixture
def key(settings: Settings, database_url: str) -> tuple[str, str]:
    """Key line-1 on each database (the PostgreSQL database is the module's: users and keys
    are removed first); the database URL and the key itself."""
    with db.session_scope(database_url) as session:
        for row in (*session.scalars(select(User)), *session.scalars(select(ApiKey))):
            session.delete(row)
        _, plain = service.create_key(session=session, name="line-1", role=Role.OPERATOR)
    return database_url, plain


def _revoked_at(url: str) -> datetime | None:
    with db.session_scope(url) as session:
        return service.get_key(session=session, name="line-1").revoked_at


def test_a_key_revoked_while_it_is_used_stays_revoked(key) -> None:
    url, plain = key
    revoked: list[datetime | None] = []

    def revoke(session: Session) -> None:
        revoked.append(service.revoke_key(session=session, name="line-1").revoked_at)

    def used() -> bool:  # its last use noted as the revoke commits
        with db.session_scope(url) as session:
            found = service.find_key(session=session, plain=plain)
            return found is not None and found.last_used_at is not None

    other = while_another_writes(url, revoke, used)

    assert other == {"result": True}
    assert _revoked_at(url) == revoked[0]
    with db.session_scope(url) as session:
        found = service.find_key(session=session, plain=plain)
        assert found is not None and found.revoked_at is not None  # refused from now on


def test_a_key_revoked_by_two_admins_at_once_keeps_the_first_revokes_time(key) -> None:
    url, _ = key
    first: list[datetime | None] = []

    def revoke() -> datetime | None:
        with db.session_scope(url) as session:
            return service.revoke_key(session=session, name="line-1").revoked_at

    other = while_another_writes(url, lambda session: first.append(
        service.revoke_key(session=session, name="line-1").revoked_at), revoke)

    assert other == {"result": first[0]}
    assert _revoked_at(url) == first[0]
