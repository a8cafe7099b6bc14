"""Roles and the principal of a request: who is asking, with which role, on which machines."""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Literal


class Role(StrEnum):
    """What a user or key may do; each role includes the ones before it."""

    VIEWER = "viewer"  # reads
    OPERATOR = "operator"  # files of the machines it is allowed, drip-feeds started and stopped
    PROGRAMMER = "programmer"  # library, approvals, rollouts (jobs on any machine), inbox decisions
    ADMIN = "admin"  # fleet, users, keys, schedules, everything

    @property
    def rank(self) -> int:
        """Its place in the order: viewer 0 ... admin 3."""
        return _ORDER.index(self)

    def allows(self, needed: Role) -> bool:
        """Whether this role includes `needed` (ADMIN allows VIEWER)."""
        return self.rank >= needed.rank

    @property
    def with_article(self) -> str:
        """`a viewer`, `an operator`: as a sentence names it."""
        return f"{'an' if self.value[0] in 'aeiou' else 'a'} {self.value}"


_ORDER = list(Role)

PrincipalKind = Literal["user", "key", "admin-key", "none"]


@dataclass(frozen=True)
class Principal:
    """Who a request comes from.

    Attributes:
        name: `alice`, `key:ci-robot`, `admin-key` (DNCQ_API_KEY or data/api-key),
            `anonymous` (authentication switched off).
        kind: a signed-in user, a named key, the admin key, or nobody checked.
        role: what it may do.
        machines: the machines it may change (files, drip-feeds); None: all of them.
    """

    name: str
    kind: PrincipalKind
    role: Role
    machines: tuple[str, ...] | None = None

    def may(self, needed: Role) -> bool:
        """Whether its role includes `needed`."""
        return self.role.allows(needed)

    def may_touch(self, machine_id: str) -> bool:
        """Whether it may change `machine_id`'s files and runs."""
        return self.machines is None or machine_id in self.machines


ANONYMOUS = Principal(name="anonymous", kind="none", role=Role.ADMIN)
"""Authentication switched off (DNCQ_AUTH=none): no check, everything allowed, as before."""

ADMIN_KEY = Principal(name="admin-key", kind="admin-key", role=Role.ADMIN)
"""The single key of DNCQ_API_KEY or data/api-key: every existing client keeps working."""


# The kinds of job (jobs.models.JobKind, a str) an operator starts, by value: the roles
# load no database model, so that a CLI command that only asks the API starts quickly.
_OPERATORS_JOBS = frozenset({"dnc_run", "restore"})


def role_for_job(kind: str) -> Role:
    """The role that starts a job of `kind`, and so may cancel it: an operator runs programs
    and restores backups (POST /api/backups/{id}/restore); rollouts are a programmer's."""
    return Role.OPERATOR if kind in _OPERATORS_JOBS else Role.PROGRAMMER


def refusal(principal: Principal, needed: Role, what: str = "this") -> str:
    """The 403's words: `this needs the programmer role; you (alice) are an operator`."""
    return (f"{what} needs the {needed.value} role; "
            f"you ({principal.name}) are {principal.role.with_article}")


def machine_refusal(principal: Principal, machine_ids: list[str]) -> str:
    """The 403's words for machines outside an operator's list."""
    allowed = ", ".join(shown_id(m) for m in principal.machines or ()) or "none"
    which = ", ".join(shown_id(m) for m in machine_ids)
    noun = "machine" if len(machine_ids) == 1 else "machines"
    return (f"you ({principal.name}) may not change {noun} {which}; "
            f"your machines: {allowed}")


def shown_id(machine_id: str) -> str:
    """A machine id as a message names it: `1010`, or `'10\\n10'` when it holds a control
    character, which would otherwise break the message's line (or a log's) as it is."""
    return machine_id if machine_id.isprintable() else repr(machine_id)
