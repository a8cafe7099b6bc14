"""Dependencies shared by the routes: settings, database session, API key, machine files."""

from __future__ import annotations

import secrets
from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Request, Security
from fastapi.security import APIKeyHeader, APIKeyQuery
from sqlalchemy.orm import Session

from jobs.api.errors import AuthError
from jobs.db import session_scope
from jobs.errors import ErrorCode
from jobs.settings import Settings


def get_settings(request: Request) -> Settings:
    """The settings the app was made with."""
    return request.app.state.settings  # type: ignore[no-any-return]


SettingsDep = Annotated[Settings, Depends(get_settings)]


def get_session(settings: SettingsDep) -> Iterator[Session]:
    """A database session for one request, committed when the route returns."""
    with session_scope(settings.resolved_database_url) as session:
        yield session


# "function": committed before the answer goes out, so a client that has it sees the change.
SessionDep = Annotated[Session, Depends(get_session, scope="function")]

_key_header = APIKeyHeader(name="X-Api-Key", auto_error=False, description="dncq API key")
_key_query = APIKeyQuery(name="apikey", auto_error=False, description="dncq API key")


def _key_given(request: Request, header_key: str | None, query_key: str | None) -> bool:
    """Whether a right key came; False without one; 403 for a wrong one.

    `KEY@MACHINE` is the key scoped to one machine, for OctoPrint clients that keep only
    the host of the URL they are given (`request.state.key_machine` says which machine).
    """
    expected: str | None = request.app.state.api_key
    given = header_key or query_key
    if not given:
        return False
    request.state.key_machine = None
    if expected is None or secrets.compare_digest(given.encode(), expected.encode()):
        return True
    key, at, machine = given.rpartition("@")
    if at and machine and secrets.compare_digest(key.encode(), expected.encode()):
        request.state.key_machine = machine
        return True
    raise AuthError(403, ErrorCode.AUTH_INVALID)


def key_machine(request: Request) -> str | None:
    """The machine a machine-scoped key (`KEY@MACHINE`) names, if the request used one."""
    return getattr(request.state, "key_machine", None)


def require_api_key(
    request: Request,
    header_key: Annotated[str | None, Security(_key_header)],
    query_key: Annotated[str | None, Security(_key_query)],
) -> None:
    """401 without a key, 403 with a wrong one; nothing when auth is switched off."""
    if request.app.state.api_key is None:
        return
    if not _key_given(request, header_key, query_key):
        raise AuthError(401, ErrorCode.AUTH_MISSING)


def optional_api_key(
    request: Request,
    header_key: Annotated[str | None, Security(_key_header)],
    query_key: Annotated[str | None, Security(_key_query)],
) -> bool:
    """Whether the caller may see details: a right key, or auth switched off; 403 when wrong."""
    if request.app.state.api_key is None:
        return True
    return _key_given(request, header_key, query_key)


KeyGivenDep = Annotated[bool, Depends(optional_api_key)]
