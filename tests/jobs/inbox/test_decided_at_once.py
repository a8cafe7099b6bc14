"""One inbox item or library version decided by two reviewers at the same moment: one
decision is made, the library gets one version, and the other reviewer is told it was
decided already, or for a library version decided the same way, answered as done (on
PostgreSQL and on SQLite)."""

from __future__ import annotations

from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import delete
from sqlalchemy.orm import Session

from jobs import db
from jobs.api.app import create_app
from jobs.inbox import service as inbox
from jobs.inbox.models import InboxItem, InboxState
from jobs.library import blobs
from jobs.library import service as library
from jobs.library.models import LibraryAssignment, LibraryProgram, VersionState
from jobs.settings import Settings
from tests.conftest import API_KEY
from tests.jobs.helpers import while_another_writes

PUNCHED = b"%\nO0010 (BRACKET)\nG0 X0\nG1 X10 F200\nM30\n%\n"


@pytest.fixture
def item(settings: Settings, database_url: str) -> tuple[Settings, int]:
    """The test's dncq on each database, its inbox holding one pending item (the PostgreSQL
    database is the module's: inbox and library are emptied first); the item's id."""
    settings = settings.model_copy(update={"database_url": database_url})
    with db.session_scope(database_url) as session:
        session.execute(delete(InboxItem))
        session.execute(delete(LibraryAssignment))
        session.execute(delete(LibraryProgram))
        received = inbox.receive(session=session, settings=settings, machine_id="m1",
                                 data=PUNCHED, name="O0010", folder="VIPROS")
        return settings, received.id


def _approve(settings: Settings, item_id: int, by: str, session: Session | None = None) -> Any:
    if session is not None:
        return inbox.approve(session=session, settings=settings, item_id=item_id,
                             decided_by=by)
    with db.session_scope(settings.resolved_database_url) as own:
        return inbox.approve(session=own, settings=settings, item_id=item_id, decided_by=by)


def _versions(settings: Settings) -> list[tuple[int, VersionState, str | None]]:
    """The library's versions of VIPROS/O0010 (none while it has no such program)."""
    with db.session_scope(settings.resolved_database_url) as session:
        return [(v.number, v.state, v.decided_by) for p in library.list_programs(
            session=session, folder="VIPROS") for v in p.versions if p.name == "O0010"]


def _state(settings: Settings, item_id: int) -> tuple[InboxState, str | None]:
    with db.session_scope(settings.resolved_database_url) as session:
        found = inbox.get(session=session, item_id=item_id)
        return found.state, found.decided_by


def test_an_item_approved_by_two_at_once_makes_one_version(item) -> None:
    settings, item_id = item

    other = while_another_writes(
        settings.resolved_database_url,
        lambda session: _approve(settings, item_id, "anna", session),
        lambda: _approve(settings, item_id, "ben"))

    error = other.get("error")
    assert isinstance(error, inbox.Undecidable) and "approved already" in str(error)
    assert _versions(settings) == [(1, VersionState.APPROVED, "anna")]
    assert _state(settings, item_id) == (InboxState.APPROVED, "anna")


def test_an_item_rejected_while_another_approves_it_stays_approved(item) -> None:
    settings, item_id = item

    def rejected() -> Any:
        with db.session_scope(settings.resolved_database_url) as session:
            return inbox.reject(session=session, item_id=item_id, decided_by="ben")

    other = while_another_writes(
        settings.resolved_database_url,
        lambda session: _approve(settings, item_id, "anna", session), rejected)

    error = other.get("error")
    assert isinstance(error, inbox.Undecidable) and "approved already" in str(error)
    assert _state(settings, item_id) == (InboxState.APPROVED, "anna")
    assert _versions(settings) == [(1, VersionState.APPROVED, "anna")]


def test_an_item_approved_while_another_rejects_it_is_left_rejected_saying_so(item) -> None:
    settings, item_id = item  # approved later it may be, by one who has seen the rejection

    other = while_another_writes(
        settings.resolved_database_url,
        lambda session: inbox.reject(session=session, item_id=item_id, decided_by="anna"),
        lambda: _approve(settings, item_id, "ben"))

    error = other.get("error")
    assert isinstance(error, inbox.Undecidable) and "rejected meanwhile" in str(error)
    assert _state(settings, item_id) == (InboxState.REJECTED, "anna")
    assert _versions(settings) == []


@pytest.fixture
def pending_version(settings: Settings, database_url: str) -> Settings:
    """The test's dncq on each database, its library holding VIPROS/O0010 v1 pending."""
    settings = settings.model_copy(update={"database_url": database_url})
    with db.session_scope(database_url) as session:
        session.execute(delete(InboxItem))
        session.execute(delete(LibraryAssignment))
        session.execute(delete(LibraryProgram))
        library.add(session=session, folder="VIPROS", name="O0010",
                    blob=blobs.put(settings, [PUNCHED]))
    return settings


def _decided(settings: Settings, state: VersionState, by: str,
             session: Session | None = None) -> Any:
    if session is not None:
        return library.decide(session=session, folder="VIPROS", name="O0010", number=1,
                              state=state, decided_by=by)
    with db.session_scope(settings.resolved_database_url) as own:
        return library.decide(session=own, folder="VIPROS", name="O0010", number=1,
                              state=state, decided_by=by)


def test_a_version_approved_by_two_at_once_is_approved_once_and_answered_to_both(
        pending_version) -> None:
    settings = pending_version

    other = while_another_writes(
        settings.resolved_database_url,
        lambda session: _decided(settings, VersionState.APPROVED, "anna", session),
        lambda: _decided(settings, VersionState.APPROVED, "ben"))

    assert "error" not in other  # done, as asked: by the other
    assert (other["result"].state, other["result"].decided_by) == (VersionState.APPROVED, "anna")
    assert _versions(settings) == [(1, VersionState.APPROVED, "anna")]


def test_a_version_rejected_while_another_approves_it_stays_approved_saying_by_whom(
        pending_version) -> None:
    settings = pending_version
    with TestClient(create_app(settings), headers={"X-Api-Key": API_KEY}) as client:
        client.get("/api/library/programs").raise_for_status()  # connected: it meets the other
        other = while_another_writes(
            settings.resolved_database_url,
            lambda session: _decided(settings, VersionState.APPROVED, "anna", session),
            lambda: client.post("/api/library/reject/VIPROS/O0010",
                                params={"version": 1, "by": "ben"}))

    answer = other["result"]
    assert (answer.status_code, answer.json()["errorCode"]) == (409, 20409)
    assert answer.json()["statusMsg"] == ("VIPROS/O0010 v1 was approved meanwhile by anna; "
                                          "it was not rejected")
    assert _versions(settings) == [(1, VersionState.APPROVED, "anna")]


def test_a_version_decided_again_later_is_decided_as_asked(pending_version) -> None:
    settings = pending_version  # by one who has seen the first decision
    _decided(settings, VersionState.APPROVED, "anna")

    again = _decided(settings, VersionState.APPROVED, "ben")
    assert (again.state, again.decided_by) == (VersionState.APPROVED, "ben")
    withdrawn = _decided(settings, VersionState.REJECTED, "carl")
    assert (withdrawn.state, withdrawn.decided_by) == (VersionState.REJECTED, "carl")
