"""Users and named API keys (admin): `/api/users`, `/api/keys`.

A key is answered once, when it is made; afterwards only its first characters are shown.
Passwords and keys never appear in an answer or in the audit trail.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

from fastapi import APIRouter, HTTPException, Request
from pydantic import BaseModel, ConfigDict, Field

from jobs.api.deps import PrincipalDep, SessionDep, note_target, requires
from jobs.api.errors import resource_errors
from jobs.api.text import CheckedRoute
from jobs.auth import service
from jobs.auth.models import ApiKey, User
from jobs.auth.roles import Role

users_router = APIRouter(prefix="/api/users", tags=["users"], route_class=CheckedRoute)
keys_router = APIRouter(prefix="/api/keys", tags=["keys"], route_class=CheckedRoute)

Machines = Field(default=None, description=(
    "The machines it may change (files, drip-feeds); null: all. Meant for operators"))


def _when(value: datetime | None) -> str | None:
    return value.isoformat() if value is not None else None


def user_view(user: User) -> dict[str, Any]:
    """A user as the API shows it: never its password hash."""
    return {"name": user.name, "role": user.role.value, "machines": user.machines,
            "disabled": user.disabled, "lockedUntil": _when(user.locked_until),
            "lastSignIn": _when(user.last_signin_at), "created": _when(user.created_at)}


def key_view(key: ApiKey) -> dict[str, Any]:
    """A key as the API lists it: its first characters, never the key or its hash."""
    return {"name": key.name, "role": key.role.value, "machines": key.machines,
            "prefix": key.prefix, "createdBy": key.created_by, "created": _when(key.created_at),
            "lastUsed": _when(key.last_used_at), "revoked": _when(key.revoked_at)}


def _unprocessable(exc: ValueError) -> HTTPException:
    return HTTPException(422, detail=str(exc))


class UserIn(BaseModel):
    """A new user."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(max_length=64)
    password: str = Field(max_length=1024)
    role: Role
    machines: list[str] | None = Machines


class UserChange(BaseModel):
    """What changes of a user; what is left out stays."""

    model_config = ConfigDict(extra="forbid")

    role: Role | None = None
    machines: list[str] | None = Machines
    password: str | None = Field(default=None, max_length=1024, description=(
        "A new password (ends a lock-out)"))
    disabled: bool | None = None


@users_router.get("", summary="Users", dependencies=[requires(Role.ADMIN)])
def list_users(session: SessionDep) -> list[dict[str, Any]]:
    return [user_view(u) for u in service.list_users(session=session)]


@users_router.post("", status_code=201, summary="Add a user",
                   dependencies=[requires(Role.ADMIN, action="users.add")])
def add_user(request: Request, session: SessionDep, user_in: UserIn) -> dict[str, Any]:
    note_target(request, user_in.name, role=user_in.role.value, machines=user_in.machines)
    with resource_errors():
        try:
            user = service.create_user(session=session, name=user_in.name,
                                       password=user_in.password, role=user_in.role,
                                       machines=user_in.machines)
        except ValueError as exc:
            raise _unprocessable(exc) from None
    return user_view(user)


@users_router.get("/{name}", summary="One user", dependencies=[requires(Role.ADMIN)])
def show_user(session: SessionDep, name: str) -> dict[str, Any]:
    with resource_errors():
        return user_view(service.get_user(session=session, name=name))


@users_router.patch("/{name}", summary="Change a user's role, machines, password; disable it",
                    dependencies=[requires(Role.ADMIN, action="users.set")])
def change_user(request: Request, session: SessionDep, name: str,
                change: UserChange) -> dict[str, Any]:
    given = change.model_fields_set
    note_target(request, name, **{k: ("***" if k == "password" else getattr(change, k))
                                  for k in sorted(given)})
    kwargs: dict[str, Any] = {k: getattr(change, k) for k in given}  # machines null: all
    with resource_errors():
        try:
            user = service.update_user(session=session, name=name, **kwargs)
        except ValueError as exc:
            raise _unprocessable(exc) from None
    return user_view(user)


@users_router.delete("/{name}", summary="Remove a user (the audit trail keeps what it did)",
                     dependencies=[requires(Role.ADMIN, action="users.delete")])
def delete_user(session: SessionDep, name: str) -> dict[str, Any]:
    with resource_errors():
        service.delete_user(session=session, name=name)
    return {"name": name, "deleted": True}


class KeyIn(BaseModel):
    """A new named key."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(max_length=64)
    role: Role
    machines: list[str] | None = Machines


@keys_router.get("", summary="Named API keys (without the keys)",
                 dependencies=[requires(Role.ADMIN)])
def list_keys(session: SessionDep, revoked: bool = True) -> list[dict[str, Any]]:
    return [key_view(k) for k in service.list_keys(session=session, revoked=revoked)]


@keys_router.post("", status_code=201,
                  summary="Make a named key: the answer holds the key, shown this once",
                  dependencies=[requires(Role.ADMIN, action="keys.add")])
def add_key(request: Request, session: SessionDep, principal: PrincipalDep,
            key_in: KeyIn) -> dict[str, Any]:
    note_target(request, key_in.name, role=key_in.role.value, machines=key_in.machines)
    with resource_errors():
        try:
            key, plain = service.create_key(session=session, name=key_in.name,
                                            role=key_in.role, machines=key_in.machines,
                                            created_by=principal.name)
        except ValueError as exc:
            raise _unprocessable(exc) from None
    return {**key_view(key), "key": plain}


@keys_router.delete("/{name}", summary="Revoke a key: refused from now on (its name is kept)",
                    dependencies=[requires(Role.ADMIN, action="keys.revoke")])
def revoke_key(session: SessionDep, name: str) -> dict[str, Any]:
    with resource_errors():
        return key_view(service.revoke_key(session=session, name=name))
