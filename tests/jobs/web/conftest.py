"""Fixtures of the dashboard's tests: the app with its pages, signed-in clients, users."""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from jobs.api.app import create_app
from jobs.settings import Settings
from jobs.web import app as web
from jobs.web import principal
from tests.conftest import API_KEY

CSRF = re.compile(r'name="csrf_token" value="([^"]+)"')


def csrf_of(page: str) -> str:
    """The CSRF token a page's forms carry."""
    found = CSRF.search(page)
    assert found, "the page has no form with a CSRF token"
    return found.group(1)


@pytest.fixture
def users(monkeypatch: pytest.MonkeyPatch) -> Callable[..., None]:
    """Factory: a named user with a role and a password, beside the admin.

    Stands in for `jobs.auth`'s users table through the dashboard's one door to it
    (`jobs.web.principal`), so that the role checks are tested.
    """
    known: dict[str, tuple[str, principal.User]] = {}
    authenticate, user_named = principal.authenticate, principal.user_named

    def fake_authenticate(*, session: Any, settings: Settings, name: str,
                          password: str) -> principal.User:
        if name in known:
            if known[name][0] != password:
                raise principal.SignInRefused("wrong name or password")
            return known[name][1]
        return authenticate(session=session, settings=settings, name=name, password=password)

    def fake_user_named(*, session: Any, name: str) -> principal.User | None:
        return known[name][1] if name in known else user_named(session=session, name=name)

    monkeypatch.setattr(principal, "authenticate", fake_authenticate)
    monkeypatch.setattr(principal, "user_named", fake_user_named)

    def add(name: str, role: principal.Role, password: str = "secret-password",
            machines: tuple[str, ...] | None = None) -> None:
        known[name] = (password, principal.User(name, role, machines))

    return add


def dashboard_app(settings: Settings) -> FastAPI:
    """The app as `dncq serve` makes it: the API and the dashboard."""
    app = create_app(settings)
    web.install(app)
    return app


@pytest.fixture
def dashboard(settings: Settings) -> Iterator[TestClient]:
    """A browser's view of the app: no key sent, redirects not followed."""
    with TestClient(dashboard_app(settings), follow_redirects=False) as client:
        yield client


def sign_in(client: TestClient, name: str = "admin", password: str = API_KEY) -> str:
    """Sign `client` in; returns the CSRF token of its session."""
    answer = client.post("/signin", data={"name": name, "password": password, "next": "/"})
    assert answer.status_code == 303, answer.text
    return csrf_of(client.get("/jobs").text)


@pytest.fixture
def admin(dashboard: TestClient) -> tuple[TestClient, str]:
    """The dashboard signed in as the admin, and its CSRF token."""
    return dashboard, sign_in(dashboard)
