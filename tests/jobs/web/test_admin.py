"""The admin pages, server side: users and keys made, changed and removed from the
dashboard, and the audit trail read, filtered, paged and exported."""

from __future__ import annotations

import csv
import io
import re

import pytest
from fastapi.testclient import TestClient

from jobs import db
from jobs.auth import audit
from jobs.auth.roles import Principal
from jobs.settings import Settings
from jobs.web import pages_admin
from jobs.web.principal import Role
from tests.jobs.web.conftest import dashboard_app, sign_in, signin_form

PASSWORD = "a-good-password"


def _add(client: TestClient, csrf: str, name: str = "alice", role: str = "operator",
         machines: str = "1010, 1011", again: str = PASSWORD) -> object:
    return client.post("/admin/users", data={
        "csrf_token": csrf, "name": name, "role": role, "machines": machines,
        "password": PASSWORD, "password_again": again})


@pytest.fixture(autouse=True)
def machines(add_machines) -> None:
    """The machines the users here are given."""
    add_machines(*({"id": m, "name": m, "model": "Mock"} for m in ("1010", "1011")))


def _client(settings: Settings) -> TestClient:
    return TestClient(dashboard_app(settings), follow_redirects=False)


def test_a_user_added_on_the_users_page_signs_in_with_its_role_and_machines(
        admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin

    answer = _add(client, csrf)

    assert answer.status_code == 303  # type: ignore[attr-defined]
    page = client.get("/admin/users").text
    assert re.search(r'data-user="alice">.*?operator.*?1010, 1011.*?active', page, re.S)
    alice = _client(settings)
    sign_in(alice, "alice", PASSWORD)
    assert "alice <span class=\"muted\">(operator)" in alice.get("/").text


def test_a_user_locked_out_by_failed_sign_ins_shows_as_locked_with_until_when(
        admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin
    _add(client, csrf)
    stranger = _client(settings)
    for _ in range(settings.signin_max_failures + 1):
        signin_form(stranger, name="alice", password="wrong", next="/")

    page = client.get("/admin/users").text

    assert re.search(r'data-user="alice">.*?locked</span> <span class="muted">until '
                     r'<time class="when" datetime="[^"]+"><span>\d{4}-\d\d-\d\d</span> '
                     r'<span>\d\d:\d\d \S+</span></time><', page, re.S)


def test_a_user_is_not_added_when_the_two_passwords_differ(
        admin: tuple[TestClient, str]) -> None:
    client, csrf = admin

    answer = _add(client, csrf, again="another-password")

    assert answer.status_code == 200  # type: ignore[attr-defined]
    assert "the two passwords differ" in answer.text  # type: ignore[attr-defined]
    assert 'data-user="alice"' not in client.get("/admin/users").text


def test_a_users_role_and_machines_are_changed_on_its_page(
        admin: tuple[TestClient, str]) -> None:
    client, csrf = admin
    _add(client, csrf)

    client.post("/admin/users/alice/set", data={"csrf_token": csrf, "role": "programmer",
                                                "machines": "all"})

    page = client.get("/admin/users").text
    assert re.search(r'data-user="alice">.*?programmer</td>\s*<td>all</td>', page, re.S)


def test_a_new_password_set_by_an_admin_replaces_the_old_one(
        admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin
    _add(client, csrf)

    client.post("/admin/users/alice/password", data={
        "csrf_token": csrf, "password": "the-new-password", "password_again": "the-new-password"})

    alice = _client(settings)
    refused = signin_form(alice, name="alice", password=PASSWORD)
    assert refused.status_code == 200 and "wrong name or password" in refused.text
    sign_in(alice, "alice", "the-new-password")


def test_a_disabled_user_is_signed_out_and_refused_until_enabled(
        admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin
    _add(client, csrf)
    alice = _client(settings)
    sign_in(alice, "alice", PASSWORD)

    client.post("/admin/users/alice/disable", data={"csrf_token": csrf})

    assert alice.get("/jobs").status_code == 303  # to the sign-in page
    assert "is disabled" in signin_form(_client(settings), name="alice", password=PASSWORD).text
    client.post("/admin/users/alice/enable", data={"csrf_token": csrf})
    sign_in(_client(settings), "alice", PASSWORD)


def test_a_removed_user_is_gone_and_cannot_sign_in(admin: tuple[TestClient, str],
                                                  settings: Settings) -> None:
    client, csrf = admin
    _add(client, csrf)

    answer = client.post("/admin/users/alice/delete", data={"csrf_token": csrf})

    assert answer.status_code == 303
    assert client.get("/admin/users/alice").status_code == 404
    assert "wrong name or password" in signin_form(
        _client(settings), name="alice", password=PASSWORD).text


def test_an_admin_may_not_disable_the_user_they_are_signed_in_as(
        admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin
    _add(client, csrf, name="root", role="admin", machines="")
    root = _client(settings)
    root_csrf = sign_in(root, "root", PASSWORD)

    answer = root.post("/admin/users/root/disable", data={"csrf_token": root_csrf})

    assert "you are signed in as root" in root.get(answer.headers["location"]).text
    assert root.get("/admin/users").status_code == 200


def test_a_new_key_is_shown_once_and_acts_with_its_role(
        admin: tuple[TestClient, str]) -> None:
    client, csrf = admin

    page = client.post("/admin/keys", data={"csrf_token": csrf, "name": "ci-robot",
                                            "role": "viewer"})

    assert page.status_code == 200 and page.headers["cache-control"] == "no-store"
    found = re.search(r"data-key>(dncq_[^<]+)<", page.text)
    assert found, "the new key is not on the page"
    key = found.group(1)
    assert key not in client.get("/admin/users").text
    assert client.get("/api/jobs", headers={"X-Api-Key": key}).status_code == 200
    assert client.post("/api/users", headers={"X-Api-Key": key}, json={
        "name": "x", "password": PASSWORD, "role": "viewer"}).status_code == 403


def test_a_revoked_key_is_refused(admin: tuple[TestClient, str]) -> None:
    client, csrf = admin
    page = client.post("/admin/keys", data={"csrf_token": csrf, "name": "old",
                                            "role": "admin"}).text
    key = re.search(r"data-key>(dncq_[^<]+)<", page).group(1)  # type: ignore[union-attr]

    client.post("/admin/keys/old/revoke", data={"csrf_token": csrf})

    assert client.get("/api/jobs", headers={"X-Api-Key": key}).status_code == 401
    assert re.search(r'data-key-name="old">.*?revoked', client.get("/admin/users").text, re.S)


@pytest.fixture
def viewer(users, settings: Settings) -> tuple[TestClient, str]:
    users("vera", Role.VIEWER)
    client = _client(settings)
    return client, sign_in(client, "vera", "secret-password")


@pytest.mark.parametrize("path", ["/admin/users", "/admin/users/vera", "/admin/audit",
                                  "/audit.csv"])
def test_a_viewer_may_not_read_the_admin_pages(viewer: tuple[TestClient, str],
                                               path: str) -> None:
    client, _ = viewer

    assert client.get(path).status_code == 403


def test_a_viewer_has_no_link_to_the_admin_pages(viewer: tuple[TestClient, str]) -> None:
    client, _ = viewer

    page = client.get("/").text

    assert 'href="/admin/users"' not in page and 'href="/admin/audit"' not in page


@pytest.mark.parametrize("path", [
    "/admin/users", "/admin/users/vera/set", "/admin/users/vera/password",
    "/admin/users/vera/disable", "/admin/users/vera/enable", "/admin/users/vera/delete",
    "/admin/keys", "/admin/keys/any/revoke"])
def test_a_viewers_admin_form_is_refused_with_403_even_with_its_token(
        viewer: tuple[TestClient, str], settings: Settings, path: str) -> None:
    client, csrf = viewer

    answer = client.post(path, data={
        "csrf_token": csrf, "name": "mallory", "role": "admin", "machines": "",
        "password": PASSWORD, "password_again": PASSWORD})

    assert answer.status_code == 403 and "you (vera) are a viewer" in answer.text
    assert signin_form(_client(settings), name="mallory",
                       password=PASSWORD).status_code == 200  # still no such user


def test_an_admin_form_without_its_csrf_token_is_refused_and_adds_nobody(
        admin: tuple[TestClient, str]) -> None:
    client, csrf = admin

    answer = _add(client, "not-the-token")

    assert answer.status_code == 403  # type: ignore[attr-defined]
    assert 'data-user="alice"' not in client.get("/admin/users").text


def test_the_audit_page_shows_the_dashboards_actions_with_who_did_them(
        admin: tuple[TestClient, str]) -> None:
    client, csrf = admin
    _add(client, csrf)
    client.post("/admin/users/alice/disable", data={"csrf_token": csrf})

    page = client.get("/admin/audit").text

    rows = re.findall(r'<td data-who>(\S+) .*?<td data-action>([^<]+)</td><td class="mono">'
                      r"([^<]+)</td>", page, re.S)
    assert rows[:2] == [("admin", "disable user", "alice"), ("admin", "add user", "alice")]


def test_the_trail_records_a_refused_form_as_refused_not_done(
        admin: tuple[TestClient, str], settings: Settings, users) -> None:
    client, csrf = admin
    users("vera", Role.VIEWER)
    vera = _client(settings)
    vera_csrf = sign_in(vera, "vera", "secret-password")

    by_service = client.post("/jobs/nosuchjob/retry", data={"csrf_token": csrf})
    by_role = vera.post("/m/1016/mkdir", data={"csrf_token": vera_csrf, "name": "X"})

    assert by_service.status_code == 303 and by_role.status_code == 403
    with db.session_scope(settings.resolved_database_url) as session:
        events = [(e.who, e.action, e.status)
                  for e in audit.list_events(session=session, limit=10)]
    assert ("admin", "retry job", 404) in events  # as the API answers a missing job
    assert ("vera", "make folder", 403) in events


def _events(settings: Settings, n: int, who: str = "bob") -> None:
    with db.session_scope(settings.resolved_database_url) as session:
        for i in range(n):
            audit.record(session=session, principal=Principal(who, "user", Role.OPERATOR),
                         address="10.0.0.9", method="POST", path="/x", status=200,
                         action="machines.put", target=f"m{i}")


def test_the_audit_page_filters_by_who_and_action(admin: tuple[TestClient, str],
                                                  settings: Settings) -> None:
    client, _ = admin
    _events(settings, 2)

    page = client.get("/admin/audit", params={"who": "bob", "action": "machines"}).text

    assert page.count("data-event=") == 2
    assert "sign in" not in re.sub(r"<select.*?</select>", "", page, flags=re.S)


def test_the_audit_page_filters_by_dates(admin: tuple[TestClient, str],
                                         settings: Settings) -> None:
    client, _ = admin
    _events(settings, 1)

    empty = client.get("/admin/audit", params={"who": "bob", "until": "2000-01-01"}).text
    shown = client.get("/admin/audit", params={"who": "bob", "since": "2000-01-01"}).text

    assert "data-event=" not in empty and "Nothing recorded that matches" in empty
    assert shown.count("data-event=") == 1


def test_the_audit_page_is_paged_newest_first(admin: tuple[TestClient, str],
                                              settings: Settings) -> None:
    client, _ = admin
    _events(settings, pages_admin.AUDIT_PAGE + 1)

    first = client.get("/admin/audit", params={"who": "bob"}).text
    second = client.get("/admin/audit", params={"who": "bob", "page": 2}).text

    assert first.count("data-event=") == pages_admin.AUDIT_PAGE and 'rel="next"' in first
    assert f">m{pages_admin.AUDIT_PAGE}<" in first
    assert second.count("data-event=") == 1 and ">m0<" in second and 'rel="next"' not in second


def test_the_audit_csv_link_exports_the_filtered_trail(admin: tuple[TestClient, str],
                                                       settings: Settings) -> None:
    client, _ = admin
    _events(settings, 3)
    page = client.get("/admin/audit", params={"who": "bob"}).text
    link = re.search(r'href="([^"]+)" download data-csv', page).group(1)  # type: ignore[union-attr]

    answer = client.get(link.replace("&amp;", "&"))

    assert answer.status_code == 200 and answer.headers["content-type"].startswith("text/csv")
    rows = list(csv.DictReader(io.StringIO(answer.text)))
    assert [r["target"] for r in rows] == ["m2", "m1", "m0"]
    assert {r["who"] for r in rows} == {"bob"}

