"""The one place the dashboard meets the auth core (`jobs.auth`): roles, principals,
sign-in, users, the addresses locked out and the audit trail.

Besides the named users, the admin key signs in as the user `admin` while no user of that
name exists: a fresh dncq has no users, and its admin must be able to make the first.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from datetime import datetime
from typing import Any

from sqlalchemy.orm import Session

from jobs.auth import audit, lockouts
from jobs.auth import service as auth
from jobs.auth.lockouts import Lockout
from jobs.auth.models import ApiKey, AuditEvent, User
from jobs.auth.roles import Principal, Role, refusal, role_for_job
from jobs.auth.service import SignInRefused
from jobs.errors import ContractError
from jobs.settings import Settings

__all__ = ["ADMIN_USER", "ApiKey", "AuditEvent", "Lockout", "Principal", "Role",
           "SignInRefused", "User", "add_key", "add_user", "audit_csv", "audit_events",
           "audit_names", "authenticate", "change_user", "counted_lockouts", "end_lockout",
           "ended_detail", "list_keys", "list_users", "principal_of", "record", "refusal",
           "remove_user", "revoke_key", "role_for_job", "stored_user", "user_named"]

ADMIN_USER = "admin"


def _admin_key_user() -> User:
    """The admin key's stand-in user: never stored."""
    return User(name=ADMIN_USER, role=Role.ADMIN, machines=None, disabled=False)


def authenticate(*, session: Session, settings: Settings, name: str, password: str,
                 address: str | None) -> User:
    """The user whose name and password these are; SignInRefused otherwise (the admin key's
    `admin` locked out after failures as a user is, from the client `address` alone)."""
    if name == ADMIN_USER and _stored(session, name) is None:
        auth.authenticate_with_key(session=session, settings=settings, name=name,
                                   given=password,
                                   key=settings.effective_api_key(create=False) or None,
                                   address=address)
        return _admin_key_user()
    return auth.authenticate(session=session, settings=settings, name=name, password=password)


def principal_of(user: User) -> Principal:
    """The principal a signed-in user acts as."""
    return auth.principal_of(user)


def _stored(session: Session, name: str) -> User | None:
    try:
        return auth.get_user(session=session, name=name)
    except ContractError:
        return None


def user_named(*, session: Session, name: str) -> User | None:
    """The user of that name (the admin key's `admin` while there is none), or None."""
    stored = _stored(session, name)
    if stored is None and name == ADMIN_USER:
        return _admin_key_user()
    return stored


def list_users(*, session: Session) -> list[User]:
    """Every user, by name."""
    return auth.list_users(session=session)


def record(*, session: Session, principal: Principal | None, address: str | None, method: str,
           path: str, status: int, action: str, target: str | None = None,
           detail: dict[str, Any] | None = None) -> None:
    """Record a state-changing action of the dashboard in the audit trail; `principal`
    None: done by nobody signed in (a name locked out by guesses)."""
    audit.record(session=session, principal=principal, address=address, method=method,
                 path=path, status=status, action=action, target=target, detail=detail)


# -- users and keys (admins) --------------------------------------------------------------
# The service's errors pass through: ValueError for what cannot be taken, ContractError for
# a name taken or not there.


def stored_user(*, session: Session, name: str) -> User:
    """The stored user of that name (ContractError PATH_NOT_FOUND when there is none)."""
    return auth.get_user(session=session, name=name)


def add_user(*, session: Session, name: str, password: str, role: Role,
             machines: Iterable[str] | None) -> User:
    """A new user with a hashed password."""
    return auth.create_user(session=session, name=name, password=password, role=role,
                            machines=machines)


def change_user(*, session: Session, name: str, role: Role | None = None,
                machines: Iterable[str] | None | auth._Unset = auth.UNSET,
                password: str | None = None, disabled: bool | None = None) -> User:
    """Change what is given of a user (machines None: all of them)."""
    return auth.update_user(session=session, name=name, role=role, machines=machines,
                            password=password, disabled=disabled)


def remove_user(*, session: Session, name: str) -> None:
    """Remove a user; the audit trail keeps what it did."""
    auth.delete_user(session=session, name=name)


def list_keys(*, session: Session) -> list[ApiKey]:
    """Every named key by name, the revoked ones too."""
    return auth.list_keys(session=session)


def add_key(*, session: Session, name: str, role: Role, machines: Iterable[str] | None,
            created_by: str) -> tuple[ApiKey, str]:
    """A new named key and the key itself, which cannot be shown again."""
    return auth.create_key(session=session, name=name, role=role, machines=machines,
                           created_by=created_by)


def revoke_key(*, session: Session, name: str) -> ApiKey:
    """Refuse the key from now on."""
    return auth.revoke_key(session=session, name=name)


# -- the audit trail (admins) -------------------------------------------------------------


def audit_events(*, session: Session, who: str | None, action: str | None,
                 since: datetime | None, until: datetime | None, limit: int,
                 offset: int = 0) -> list[AuditEvent]:
    """Events newest first, filtered, one page of them."""
    return audit.list_events(session=session, who=who, action=action, since=since,
                             until=until, limit=limit, offset=offset)


def audit_names(*, session: Session) -> tuple[list[str], list[str]]:
    """The principals and the actions the trail holds, for the filters."""
    return audit.names_seen(session=session)


def audit_csv(events: Iterable[AuditEvent]) -> Iterator[str]:
    """The events as CSV, a header row first."""
    return audit.as_csv(events)


def counted_lockouts(*, session: Session, settings: Settings) -> list[Lockout]:
    """The client addresses locked out, or with failures counted, for wrong API keys or
    sign-ins as `admin` with the admin key."""
    return lockouts.counted_now(session=session, settings=settings)


ended_detail = lockouts.ended_detail  # an end's audit detail, as the API writes it


def end_lockout(*, session: Session, address: str,
                kept: lockouts.KeptLocked) -> list[Lockout]:
    """End `address`'s lock-outs as the API's DELETE does: in the database (the caller
    commits) and in `kept`, the addresses the serving API process keeps as locked."""
    return lockouts.end_kept(session=session, address=address, kept=kept)
