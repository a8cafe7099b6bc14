"""The one place the dashboard meets the auth core (`jobs.auth`): roles, principals,
sign-in, users and the audit trail.

Besides the named users, the admin key signs in as the user `admin` while no user of that
name exists: a fresh dncq has no users, and its admin must be able to make the first.
"""

from __future__ import annotations

import secrets
from typing import Any

from sqlalchemy.orm import Session

from jobs.auth import audit
from jobs.auth import service as auth
from jobs.auth.models import User
from jobs.auth.roles import Principal, Role
from jobs.auth.service import SignInRefused
from jobs.errors import ContractError
from jobs.settings import Settings

__all__ = ["ADMIN_USER", "Principal", "Role", "SignInRefused", "User", "authenticate",
           "list_users", "principal_of", "record", "user_named"]

ADMIN_USER = "admin"


def _admin_key_user() -> User:
    """The admin key's stand-in user: never stored."""
    return User(name=ADMIN_USER, role=Role.ADMIN, machines=None, disabled=False)


def authenticate(*, session: Session, settings: Settings, name: str, password: str) -> User:
    """The user whose name and password these are; SignInRefused otherwise."""
    if name == ADMIN_USER and _stored(session, name) is None:
        key = settings.effective_api_key(create=False)
        if key and secrets.compare_digest(password.encode(), key.encode()):
            return _admin_key_user()
        raise SignInRefused("wrong", auth.WRONG)
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


def record(*, session: Session, principal: Principal, address: str | None, method: str,
           path: str, status: int, action: str, target: str | None = None,
           detail: dict[str, Any] | None = None) -> None:
    """Record a state-changing action of the dashboard in the audit trail."""
    audit.record(session=session, principal=principal, address=address, method=method,
                 path=path, status=status, action=action, target=target, detail=detail)
