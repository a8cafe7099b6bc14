"""The Users page's locked-out addresses: each listed with what it counts and until when,
its lock-out ended by an admin as the API ends it, and in the audit trail as the API's."""

from __future__ import annotations

import html
import re
from collections.abc import Iterator

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from jobs import db
from jobs.auth import audit
from jobs.auth.roles import Role
from jobs.settings import Settings
from tests.conftest import API_KEY
from tests.jobs.web.conftest import dashboard_app, sign_in, signin_form

LOCKED = "203.0.113.9"
ADMIN_HOST = "10.0.0.7"


@pytest.fixture
def app(settings: Settings) -> FastAPI:
    return dashboard_app(settings)


def _from(app: FastAPI, address: str) -> TestClient:
    """A browser (or a script) whose requests come from `address`."""
    return TestClient(app, follow_redirects=False, client=(address, 40000))


@pytest.fixture
def admin(app: FastAPI) -> Iterator[tuple[TestClient, str]]:
    """The dashboard signed in as the admin from another address than the locked one."""
    with _from(app, ADMIN_HOST) as client:
        yield client, sign_in(client)


def _lock_sign_in(client: TestClient, settings: Settings) -> None:
    for _ in range(settings.signin_max_failures):
        signin_form(client, name="admin", password="a stale copy of the key")


def _lock_keys(client: TestClient, settings: Settings) -> None:
    for n in range(settings.signin_max_failures):
        client.get("/api/machines", headers={"X-Api-Key": f"a-guess-{n}"})


def _end_form(page: str, address: str) -> str:
    """The action of the End lock-out form of `address`'s row, as the page writes it."""
    row = re.search(rf'<tr data-lockout="{re.escape(address)}".*?</tr>', page, re.S)
    assert row, f"no row of {address}"
    found = re.search(r'<form method="post" action="([^"]+)"', row.group(0))
    assert found and "End lock-out" in row.group(0)
    return html.unescape(found.group(1))


def _ended(settings: Settings) -> list[tuple[str, str, int, str | None, object]]:
    with db.session_scope(settings.resolved_database_url) as session:
        return [(e.who, e.action, e.status, e.target, e.detail)
                for e in reversed(audit.list_events(session=session, action="lockouts.end"))]


def _listed(page: str) -> list[tuple[str, str, str, bool]]:
    """Each listed count: its address, what it counts, its failures and whether locked."""
    return [(a, c, f, "s-stopped" in rest) for a, c, f, rest in
            re.findall(r'<tr data-lockout="([^"]+)" data-counted="([^"]+)"><td class="mono">'
                       r'[^<]*</td><td>[^<]*</td><td>(\d+)</td>(.*?)</tr>', page, re.S)]


def test_the_users_page_lists_each_address_with_what_it_counts_and_until_when(
        app: FastAPI, admin: tuple[TestClient, str], settings: Settings) -> None:
    client, _ = admin
    with _from(app, LOCKED) as locked, _from(app, "10.0.0.8") as typo:
        _lock_sign_in(locked, settings)
        _lock_keys(locked, settings)
        typo.get("/api/machines", headers={"X-Api-Key": "a-typo"})

        page = client.get("/admin/users").text

    # A locked address shows the failures that locked it out (the API lists them so too).
    most = str(settings.signin_max_failures)
    assert _listed(page) == [(LOCKED, "api keys", most, True),
                             (LOCKED, "admin sign-ins", most, True),
                             ("10.0.0.8", "api keys", "1", False)]
    locked_row = re.search(rf'data-lockout="{LOCKED}".*?</tr>', page, re.S).group(0)  # type: ignore[union-attr]
    assert re.search(r'until <time class="when" datetime="[^"]+"><span>\d{4}-\d\d-\d\d</span> '
                     r'<span>\d\d:\d\d \S+</span></time>', locked_row)


def test_the_users_page_says_when_no_address_is_counted(admin: tuple[TestClient, str]) -> None:
    client, _ = admin

    page = client.get("/admin/users").text

    assert "Locked-out addresses" in page
    assert "No address is locked out or has failures counted." in page


def test_ending_an_addresses_lock_out_on_the_users_page_lets_it_sign_in_again(
        app: FastAPI, admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin
    with _from(app, LOCKED) as locked:
        _lock_sign_in(locked, settings)
        assert signin_form(locked, name="admin", password=API_KEY).status_code == 200
        action = _end_form(client.get("/admin/users").text, LOCKED)

        answer = client.post(action, data={"csrf_token": csrf})

        assert answer.status_code == 303
        assert "Ended the lock-out of 203.0.113.9 (admin sign-ins)" in client.get(
            answer.headers["location"]).text
        assert signin_form(locked, name="admin", password=API_KEY).status_code == 303
    assert f'data-lockout="{LOCKED}"' not in client.get("/admin/users").text


def test_ending_a_wrong_key_lock_out_on_the_users_page_takes_the_addresses_key_at_once(
        app: FastAPI, admin: tuple[TestClient, str], settings: Settings) -> None:
    # This process keeps the locked address in memory: the page ends it there too, as the
    # API's DELETE does, where a database row removed alone left it refused for 10 s more.
    client, csrf = admin
    with _from(app, LOCKED) as locked:
        _lock_keys(locked, settings)
        assert locked.get("/api/machines", headers={"X-Api-Key": API_KEY}).status_code == 429

        client.post(_end_form(client.get("/admin/users").text, LOCKED),
                    data={"csrf_token": csrf})

        assert locked.get("/api/machines", headers={"X-Api-Key": API_KEY}).status_code == 200


def test_an_admin_on_the_locked_address_itself_ends_its_key_lock_out_on_the_dashboard(
        app: FastAPI, settings: Settings) -> None:
    # The API refuses the admin key from there; the dashboard's pages take no key.
    with _from(app, LOCKED) as locked:
        _lock_keys(locked, settings)
        csrf = sign_in(locked)

        locked.post(_end_form(locked.get("/admin/users").text, LOCKED),
                    data={"csrf_token": csrf})

        assert locked.get("/api/machines", headers={"X-Api-Key": API_KEY}).status_code == 200


def test_an_ipv6_hosts_lock_out_is_ended_from_its_64_row(
        app: FastAPI, admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin
    with _from(app, "2001:db8:7:1::5") as locked:
        _lock_keys(locked, settings)
        action = _end_form(client.get("/admin/users").text, "2001:db8:7:1::/64")

        client.post(action, data={"csrf_token": csrf})

        assert locked.get("/api/machines", headers={"X-Api-Key": API_KEY}).status_code == 200
    assert "2001:db8:7:1::/64" not in client.get("/admin/users").text


def test_the_end_of_a_lock_out_is_in_the_audit_trail_as_the_apis_is(
        app: FastAPI, admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin
    with _from(app, LOCKED) as locked:
        _lock_sign_in(locked, settings)
        client.post(_end_form(client.get("/admin/users").text, LOCKED),
                    data={"csrf_token": csrf})

    [(who, action, status, target, detail)] = _ended(settings)
    assert (who, action, status, target) == ("admin", "lockouts.end", 200, LOCKED)
    assert list(detail["ended"]) == ["admin sign-ins"]  # type: ignore[index]
    assert detail["ended"]["admin sign-ins"]  # type: ignore[index]  # until when it was


def test_ending_an_address_with_nothing_counted_says_so_and_is_recorded_with_the_apis_404(
        admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin
    api = client.delete("/api/lockouts/198.51.100.1", headers={"X-Api-Key": API_KEY})

    answer = client.post("/admin/lockouts/198.51.100.1/end", data={"csrf_token": csrf})

    assert answer.status_code == 303
    assert ("No lock-out ended: no wrong API keys nor failed sign-ins are counted for "
            "198.51.100.1") in client.get(answer.headers["location"]).text
    assert [e[:4] for e in _ended(settings)] == [
        ("admin-key", "lockouts.end", api.status_code, "198.51.100.1"),
        ("admin", "lockouts.end", 404, "198.51.100.1")]


def test_a_viewer_may_not_end_a_lock_out_and_is_recorded_refused(
        app: FastAPI, settings: Settings, users) -> None:
    users("vera", Role.VIEWER)
    with _from(app, LOCKED) as locked, _from(app, ADMIN_HOST) as vera:
        _lock_sign_in(locked, settings)
        csrf = sign_in(vera, "vera", "secret-password")

        answer = vera.post(f"/admin/lockouts/{LOCKED}/end", data={"csrf_token": csrf})

        assert answer.status_code == 403 and "you (vera) are a viewer" in answer.text
        assert signin_form(locked, name="admin", password=API_KEY).status_code == 200
    assert [e[:4] for e in _ended(settings)] == [("vera", "lockouts.end", 403, LOCKED)]


def test_a_lock_out_end_without_its_csrf_token_is_refused_and_ends_nothing(
        app: FastAPI, admin: tuple[TestClient, str], settings: Settings) -> None:
    client, _ = admin
    with _from(app, LOCKED) as locked:
        _lock_sign_in(locked, settings)

        answer = client.post(f"/admin/lockouts/{LOCKED}/end", data={"csrf_token": "stale"})

        assert answer.status_code == 403
        assert signin_form(locked, name="admin", password=API_KEY).status_code == 200
