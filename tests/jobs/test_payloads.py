"""A program is kept once in the database, however many jobs send it, and two requests that
send the same program at the same moment both make their job."""

from __future__ import annotations

import threading
from typing import Any

import pytest
from sqlalchemy import func, select

from jobs import db, service
from jobs.models import Payload
from jobs.settings import Settings

PROGRAM = b"%\nO0077\nG0 X0\nM30\n%\n"


@pytest.fixture(params=["postgresql", "sqlite"])
def url(request: pytest.FixtureRequest, settings: Settings) -> str:
    if request.param == "sqlite":
        return settings.resolved_database_url
    return str(request.getfixturevalue("postgres_url"))


def test_the_same_program_stored_twice_is_kept_once(url: str) -> None:
    with db.session_scope(url) as session:
        first = service.store_payload(session=session, data=PROGRAM)
    with db.session_scope(url) as session:
        assert service.store_payload(session=session, data=PROGRAM) == first
        assert session.scalar(select(func.count()).select_from(Payload)
                              .where(Payload.id == first)) == 1


def test_two_requests_storing_the_same_program_at_once_both_succeed(url: str) -> None:
    other: dict[str, Any] = {}

    def store_alone() -> None:
        try:
            with db.session_scope(url) as session:
                other["id"] = service.store_payload(session=session, data=PROGRAM + b"\n")
        except Exception as exc:  # noqa: BLE001 - the test reports it
            other["error"] = exc

    storing = threading.Thread(target=store_alone)
    with db.session_scope(url) as session:
        mine = service.store_payload(session=session, data=PROGRAM + b"\n")
        storing.start()
        storing.join(0.5)  # the other request meets this one, not committed yet
    storing.join(30)
    assert not storing.is_alive()
    assert other == {"id": mine}
    with db.session_scope(url) as session:
        assert session.scalar(select(Payload.size).where(Payload.id == mine)) == len(PROGRAM) + 1
