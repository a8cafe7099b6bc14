"""Fixtures of the auth tests: named keys of each role, and an app that sends none itself."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import pytest
from fastapi.testclient import TestClient

from jobs import db
from jobs.api.app import create_app
from jobs.auth import service
from jobs.auth.roles import Role
from jobs.settings import Settings

MACHINES = [{"id": "1010", "name": "Lathe", "model": "Mock"},
            {"id": "1011", "name": "Mill", "model": "Mock"}]


@pytest.fixture
def make_key(settings: Settings) -> Callable[..., str]:
    """Factory: a named key of `role` (only on `machines` when given); the key itself."""
    made = 0

    def make(role: Role, machines: list[str] | None = None, name: str | None = None) -> str:
        nonlocal made
        made += 1
        with db.session_scope(settings.resolved_database_url) as session:
            _, plain = service.create_key(session=session, name=name or f"{role}-{made}",
                                          role=role, machines=machines)
        return plain

    return make


@pytest.fixture
def api(settings: Settings, add_machines) -> Iterator[TestClient]:
    """The API with machines 1010 and 1011; each request says its own key. Batch calls
    answer at once (no worker runs their targets), and backupFiles' download breaks off
    as soon as it begins (no worker fetches it): a server that raises answers 500 here."""
    add_machines(*MACHINES)
    quick = settings.model_copy(update={"batch_wait_s": 0.05, "busy_wait_s": 0.05})
    with TestClient(create_app(quick), raise_server_exceptions=False) as c:
        yield c


@pytest.fixture
def keys(make_key) -> dict[Role, str]:
    """One named key of each role, on every machine."""
    return {role: make_key(role) for role in Role}
