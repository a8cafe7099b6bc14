"""Users' passwords: hashed with argon2id, never kept or shown plain; sign-in refused for a
wrong password, a disabled user, and after five failures within the window until the
lock-out ends."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import pytest

from jobs import db
from jobs.auth import service
from jobs.auth.models import User
from jobs.auth.roles import Role
from jobs.auth.service import SignInRefused

PASSWORD = "correct horse battery"


class Clock:
    """The time jobs.auth.service reads, moved by the test."""

    def __init__(self) -> None:
        self.now = datetime(2026, 12, 1, 8, 0, tzinfo=UTC)

    def __call__(self) -> datetime:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += timedelta(seconds=seconds)


@pytest.fixture
def clock(monkeypatch) -> Clock:
    c = Clock()
    monkeypatch.setattr(service, "utcnow", c)
    return c


@pytest.fixture
def session(settings):
    with db.session_scope(settings.resolved_database_url) as s:
        yield s


@pytest.fixture
def alice(settings, add_machines) -> User:
    """An operator on machine 1010, committed."""
    add_machines({"id": "1010", "name": "Lathe", "model": "Mock"})
    with db.session_scope(settings.resolved_database_url) as s:
        return service.create_user(session=s, name="alice", password=PASSWORD,
                                   role=Role.OPERATOR, machines=["1010"])


def _sign_in(session, settings, password: str, name: str = "alice") -> User:
    return service.authenticate(session=session, settings=settings, name=name,
                                password=password)


def test_a_password_is_kept_as_an_argon2id_hash_never_plain(alice) -> None:
    assert alice.password_hash.startswith("$argon2id$")
    assert PASSWORD not in alice.password_hash


def test_two_users_with_the_same_password_get_different_hashes(session, alice) -> None:
    bob = service.create_user(session=session, name="bob", password=PASSWORD, role=Role.VIEWER)

    assert bob.password_hash != alice.password_hash


def test_the_right_password_signs_in_as_the_users_principal(session, settings, alice) -> None:
    user = _sign_in(session, settings, PASSWORD)

    principal = service.principal_of(user)
    assert (principal.name, principal.kind, principal.role, principal.machines) == (
        "alice", "user", Role.OPERATOR, ("1010",))


def test_a_wrong_password_and_an_unknown_name_are_refused_in_the_same_words(
        session, settings, alice) -> None:
    with pytest.raises(SignInRefused) as wrong:
        _sign_in(session, settings, "not it")
    with pytest.raises(SignInRefused) as unknown:
        _sign_in(session, settings, PASSWORD, name="mallory")

    assert wrong.value.reason == unknown.value.reason == service.WRONG
    assert wrong.value.reason.startswith("wrong name or password")


def test_a_locked_out_user_is_refused_in_the_words_an_unknown_name_is(
        session, settings, alice, clock) -> None:
    # Only names that exist are ever locked: other words for a lock-out gave them away.
    _fail(session, settings, settings.signin_max_failures + 1)
    _fail(session, settings, settings.signin_max_failures + 1, name="mallory")

    with pytest.raises(SignInRefused) as locked:
        _sign_in(session, settings, PASSWORD)
    with pytest.raises(SignInRefused) as unknown:
        _sign_in(session, settings, PASSWORD, name="mallory")

    assert locked.value.kind == "locked"  # still locked, for the audit and the admin
    assert locked.value.reason == unknown.value.reason == service.WRONG


def test_a_disabled_user_is_refused_with_the_right_password(session, settings, alice) -> None:
    service.update_user(session=session, name="alice", disabled=True)

    with pytest.raises(SignInRefused) as refused:
        _sign_in(session, settings, PASSWORD)

    assert refused.value.kind == "disabled"


def _fail(session, settings, times: int, name: str = "alice") -> None:
    for _ in range(times):
        with pytest.raises(SignInRefused):
            _sign_in(session, settings, "not it", name=name)


def test_five_failures_within_the_window_lock_the_user_out_even_with_the_right_password(
        session, settings, alice, clock) -> None:
    _fail(session, settings, settings.signin_max_failures)

    with pytest.raises(SignInRefused) as refused:
        _sign_in(session, settings, PASSWORD)

    assert refused.value.kind == "locked"
    assert refused.value.locked_until == clock.now + timedelta(seconds=settings.signin_lockout_s)


def test_the_failure_count_is_kept_when_the_callers_transaction_rolls_back(
        settings, alice, clock) -> None:
    for _ in range(settings.signin_max_failures):
        with pytest.raises(SignInRefused), \
                db.session_scope(settings.resolved_database_url) as s:
            _sign_in(s, settings, "not it")

    with db.session_scope(settings.resolved_database_url) as s:
        assert service.get_user(session=s, name="alice").locked_until is not None


def test_the_lock_out_ends_after_signin_lockout_s(session, settings, alice, clock) -> None:
    _fail(session, settings, settings.signin_max_failures)

    clock.advance(settings.signin_lockout_s + 1)

    assert _sign_in(session, settings, PASSWORD).name == "alice"


def test_after_a_lock_out_ends_a_wrong_password_counts_from_one(
        session, settings, alice, clock) -> None:
    # The failures that locked the user out are kept for the admin to see; once the
    # lock-out ends they are paid for, though their window has not ended yet.
    short = settings.model_copy(update={"signin_lockout_s": 60.0})
    _fail(session, short, short.signin_max_failures)
    assert service.get_user(session=session, name="alice").failed_signins == \
        short.signin_max_failures

    clock.advance(61)
    _fail(session, short, 1)

    assert _sign_in(session, short, PASSWORD).name == "alice"


def test_failures_spread_wider_than_the_window_do_not_lock(session, settings, alice,
                                                          clock) -> None:
    _fail(session, settings, settings.signin_max_failures - 1)
    clock.advance(settings.signin_window_s + 1)
    _fail(session, settings, 1)

    assert _sign_in(session, settings, PASSWORD).name == "alice"


def test_a_success_resets_the_failure_count(session, settings, alice, clock) -> None:
    _fail(session, settings, settings.signin_max_failures - 1)
    _sign_in(session, settings, PASSWORD)
    _fail(session, settings, settings.signin_max_failures - 1)

    assert _sign_in(session, settings, PASSWORD).name == "alice"


def test_a_new_password_ends_a_lock_out(session, settings, alice, clock) -> None:
    _fail(session, settings, settings.signin_max_failures)

    service.update_user(session=session, name="alice", password="a brand new one")

    assert _sign_in(session, settings, "a brand new one").name == "alice"


def test_a_password_shorter_than_eight_characters_is_refused(session) -> None:
    with pytest.raises(ValueError, match="at least 8"):
        service.create_user(session=session, name="carol", password="short", role=Role.VIEWER)
