"""The one place the dashboard meets the auth core (`jobs.auth`): roles, principals,
sign-in, users and the audit trail.

Until `jobs.auth` is part of the tree, this module defines the few names of its interface
the dashboard uses, with the admin API key as the password of the one user "admin".
"""

from __future__ import annotations

import logging
import secrets
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, Literal

from sqlalchemy.orm import Session

from jobs.settings import Settings

log = logging.getLogger(__name__)

ADMIN_USER = "admin"


class Role(StrEnum):
    """What a principal may do; each includes the ones before it."""

    VIEWER = "viewer"  # reads
    OPERATOR = "operator"  # files on its machines, drip-feeds
    PROGRAMMER = "programmer"  # library, approvals, rollouts
    ADMIN = "admin"  # fleet, users, keys, schedules, everything

    def allows(self, needed: Role) -> bool:
        """Whether this role includes `needed`."""
        order = list(Role)
        return order.index(self) >= order.index(needed)


@dataclass(frozen=True)
class Principal:
    """Who makes a request, and what they may do."""

    name: str
    kind: Literal["user", "key", "admin-key", "none"]
    role: Role
    machines: tuple[str, ...] | None = None  # an operator's allowed machines; None: all

    def may(self, needed: Role) -> bool:
        """Whether the role includes `needed`."""
        return self.role.allows(needed)

    def may_touch(self, machine_id: str) -> bool:
        """Whether the machine is one of those allowed."""
        return self.machines is None or machine_id in self.machines


class SignInRefused(Exception):
    """A sign-in refused; `reason` is what the user is told."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


@dataclass(frozen=True)
class User:
    """A named user, as far as the dashboard reads one."""

    name: str
    role: Role
    machines: tuple[str, ...] | None = None
    disabled: bool = False


def authenticate(*, session: Session, settings: Settings, name: str, password: str) -> User:
    """The user whose name and password these are; SignInRefused otherwise."""
    key = settings.effective_api_key(create=False)
    if name == ADMIN_USER and key and secrets.compare_digest(password.encode(), key.encode()):
        return User(ADMIN_USER, Role.ADMIN)
    raise SignInRefused("wrong name or password")


def principal_of(user: User) -> Principal:
    """The principal a signed-in user acts as."""
    return Principal(user.name, "user", user.role, user.machines)


def user_named(*, session: Session, name: str) -> User | None:
    """The user of that name, None when there is none (or it was removed)."""
    return User(ADMIN_USER, Role.ADMIN) if name == ADMIN_USER else None


def list_users(*, session: Session) -> list[User]:
    """Every user, by name."""
    return [User(ADMIN_USER, Role.ADMIN)]


def record(*, session: Session, principal: Principal, address: str | None, method: str,
           path: str, status: int, action: str, target: str | None = None,
           detail: dict[str, Any] | None = None) -> None:
    """Record a state-changing action in the audit trail (here: the log)."""
    log.info("audit: %s from %s: %s %s -> %d (%s %s)", principal.name, address, method, path,
             status, action, target or "")
