"""A user changed from two places at the same moment (sign-ins that fail, an admin's
changes, a removal): each failure counts, a change is checked against the user as the other
left it, and one that meets a removal is told the user is gone (on PostgreSQL and on
SQLite)."""

from __future__ import annotations

from datetime import timedelta
from typing import Any

import pytest
from sqlalchemy import delete, select, update
from sqlalchemy.orm import Session

from jobs import db
from jobs.auth import service
from jobs.auth.models import ApiKey, SignInCount, User
from jobs.auth.roles import Role
from jobs.errors import ContractError, ErrorCode
from jobs.fleet import registry
from jobs.models import utcnow
from jobs.settings import Settings
from tests.jobs.helpers import while_another_writes

PASSWORD = "correct horse battery"


@pytest.fixture
def on_database(settings: Settings, database_url: str) -> Settings:
    """The test's dncq on each database with machine 1010 and operator alice on every
    machine (the PostgreSQL database is the module's: users and keys are removed first)."""
    settings = settings.model_copy(update={"database_url": database_url})
    with db.session_scope(database_url) as session:
        for row in (*session.scalars(select(User)), *session.scalars(select(ApiKey))):
            session.delete(row)
        registry.upsert(session=session, machine_in=registry.MachineIn(
            id="1010", name="Lathe", model="Mock"), data_dir=settings.data_dir)
        service.create_user(session=session, name="alice", password=PASSWORD,
                            role=Role.OPERATOR)
    return settings


def _alice(settings: Settings) -> User:
    with db.session_scope(settings.resolved_database_url) as session:
        user = service.get_user(session=session, name="alice")
        session.expunge(user)
        return user


def _signs_in_wrongly(settings: Settings) -> Any:
    def sign_in() -> None:
        with db.session_scope(settings.resolved_database_url) as session:
            service.authenticate(session=session, settings=settings, name="alice",
                                 password="not it")
    return sign_in


def test_two_wrong_sign_ins_at_once_both_count_towards_the_lock_out(on_database) -> None:
    def failed_meanwhile(session: Session) -> None:  # what another wrong sign-in writes
        session.execute(update(User).where(User.name == "alice").values(
            failed_signins=1, failed_since=utcnow()))

    other = while_another_writes(on_database.resolved_database_url, failed_meanwhile,
                                 _signs_in_wrongly(on_database))

    error = other.get("error")
    assert isinstance(error, service.SignInRefused) and error.kind == "wrong"
    assert _alice(on_database).failed_signins == 2  # not 1: a guess at once is no free guess


def test_a_wrong_sign_in_that_meets_the_lock_out_is_refused_as_locked(on_database) -> None:
    def locked_meanwhile(session: Session) -> None:  # what another failure that locks writes
        session.execute(update(User).where(User.name == "alice").values(
            failed_signins=on_database.signin_max_failures, failed_since=utcnow(),
            locked_until=utcnow() + timedelta(seconds=on_database.signin_lockout_s)))

    other = while_another_writes(on_database.resolved_database_url, locked_meanwhile,
                                 _signs_in_wrongly(on_database))

    error = other.get("error")
    assert isinstance(error, service.SignInRefused) and error.kind == "locked"
    assert _alice(on_database).failed_signins == on_database.signin_max_failures  # the
    # lock-out's count, not one more


ADDRESS = "10.0.0.7"
KEY_ROW = f"admin from {ADDRESS}"  # the key's failures are counted per client address


def _admin_key_failures(settings: Settings) -> int:
    with db.session_scope(settings.resolved_database_url) as session:
        return session.get_one(SignInCount, KEY_ROW).failed_signins


def _signs_in_with_a_wrong_key(settings: Settings) -> Any:
    def sign_in() -> None:
        with db.session_scope(settings.resolved_database_url) as session:
            service.authenticate_with_key(session=session, settings=settings, name="admin",
                                          given="not it", key="the-admin-key-0123",
                                          address=ADDRESS)
    return sign_in


@pytest.mark.parametrize("counted_before", [False, True],
                         ids=["the first failures", "failures after others"])
def test_two_wrong_admin_key_sign_ins_at_once_both_count_towards_the_lock_out(
        on_database, counted_before) -> None:
    url = on_database.resolved_database_url
    with db.session_scope(url) as session:
        session.execute(delete(SignInCount))
        if counted_before:
            session.add(SignInCount(name=KEY_ROW, failed_signins=0))

    def failed_meanwhile(session: Session) -> None:  # what another wrong sign-in writes
        session.merge(SignInCount(name=KEY_ROW, failed_signins=1, failed_since=utcnow()))
        session.flush()

    other = while_another_writes(url, failed_meanwhile, _signs_in_with_a_wrong_key(on_database))

    error = other.get("error")
    assert isinstance(error, service.SignInRefused) and error.kind == "wrong"
    assert _admin_key_failures(on_database) == 2


def test_a_role_and_a_machine_list_changed_at_once_never_make_an_admin_with_a_list(
        on_database) -> None:
    def limited_meanwhile(session: Session) -> None:
        service.update_user(session=session, name="alice", machines=["1010"])

    def made_admin() -> User:
        with db.session_scope(on_database.resolved_database_url) as session:
            return service.update_user(session=session, name="alice", role=Role.ADMIN)

    other = while_another_writes(on_database.resolved_database_url, limited_meanwhile,
                                 made_admin)

    assert isinstance(other.get("error"), ValueError)  # "clear it in the same change"
    alice = _alice(on_database)
    assert (alice.role, alice.machines) == (Role.OPERATOR, ["1010"])


def test_a_user_changed_while_another_admin_removes_it_is_not_found(on_database) -> None:
    def removed_meanwhile(session: Session) -> None:
        service.delete_user(session=session, name="alice")

    def disabled() -> User:
        with db.session_scope(on_database.resolved_database_url) as session:
            return service.update_user(session=session, name="alice", disabled=True)

    other = while_another_writes(on_database.resolved_database_url, removed_meanwhile,
                                 disabled)

    error = other.get("error")
    assert isinstance(error, ContractError) and error.code is ErrorCode.PATH_NOT_FOUND


def test_a_user_removed_by_two_admins_at_once_is_not_found_for_the_second(
        on_database) -> None:
    def removed_meanwhile(session: Session) -> None:
        service.delete_user(session=session, name="alice")

    def removed() -> None:
        with db.session_scope(on_database.resolved_database_url) as session:
            service.delete_user(session=session, name="alice")

    other = while_another_writes(on_database.resolved_database_url, removed_meanwhile,
                                 removed)

    error = other.get("error")
    assert isinstance(error, ContractError) and error.code is ErrorCode.PATH_NOT_FOUND


def test_the_admin_key_counts_of_addresses_whose_window_and_lock_out_ended_are_forgotten(
        on_database) -> None:
    """Else every address that ever guessed at the key on the sign-in page kept a row."""
    url, now = on_database.resolved_database_url, utcnow()
    window = timedelta(seconds=on_database.signin_window_s)
    with db.session_scope(url) as session:
        session.execute(delete(SignInCount))
        session.add_all([
            SignInCount(name="admin from 10.0.1.1", failed_signins=2,
                        failed_since=now - 2 * window),
            SignInCount(name="admin from 10.0.1.2", failed_signins=0,
                        locked_until=now - window / 10),
            SignInCount(name="admin from 10.0.1.3", failed_signins=2,
                        failed_since=now - window / 2),
            SignInCount(name="admin from 10.0.1.4", failed_signins=0,
                        locked_until=now + window)])

    with pytest.raises(service.SignInRefused), db.session_scope(url) as session:
        service.authenticate_with_key(session=session, settings=on_database, name="admin",
                                      given="not it", key="the-admin-key-0123",
                                      address=ADDRESS)
    with db.session_scope(url) as session:
        kept = sorted(session.scalars(select(SignInCount.name)))

    assert kept == [KEY_ROW, "admin from 10.0.1.3", "admin from 10.0.1.4"]
    assert _admin_key_failures(on_database) == 1
