"""Fixtures of the dashboard's tests: the app with its pages, signed-in clients, users."""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator

import httpx
import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from jobs.api.app import create_app
from jobs.auth import service as auth
from jobs.auth.roles import Role
from jobs.db import session_scope
from jobs.settings import Settings
from jobs.web import app as web
from tests.conftest import API_KEY

CSRF = re.compile(r'name="csrf_token" value="([^"]+)"')


def csrf_of(page: str) -> str:
    """The CSRF token a page's forms carry."""
    found = CSRF.search(page)
    assert found, "the page has no form with a CSRF token"
    return found.group(1)


@pytest.fixture
def users(settings: Settings) -> Callable[..., None]:
    """Factory: a named user with a role and a password, beside the admin (the admin key)."""

    def add(name: str, role: Role, password: str = "secret-password",
            machines: tuple[str, ...] | None = None) -> None:
        with session_scope(settings.resolved_database_url) as session:
            auth.create_user(session=session, name=name, password=password, role=role,
                             machines=list(machines) if machines is not None else None)

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


def signin_form(client: httpx.Client, **fields: str) -> httpx.Response:
    """The sign-in form sent as a browser sends it: opened first, then sent with its token."""
    token = csrf_of(client.get("/signin").text)
    return client.post("/signin", data={"csrf_token": token, **fields})


def sign_in(client: TestClient, name: str = "admin", password: str = API_KEY) -> str:
    """Sign `client` in; returns the CSRF token of its session."""
    answer = signin_form(client, name=name, password=password, next="/")
    assert answer.status_code == 303, answer.text
    return csrf_of(client.get("/jobs").text)


@pytest.fixture
def admin(dashboard: TestClient) -> tuple[TestClient, str]:
    """The dashboard signed in as the admin, and its CSRF token."""
    return dashboard, sign_in(dashboard)
