"""Signing in and out of the dashboard: cookies, CSRF, expiry, where sign-in leads."""

from __future__ import annotations

from collections.abc import Callable
from datetime import datetime, timedelta
from typing import Any

import pytest
from argon2 import PasswordHasher
from fastapi.testclient import TestClient

from jobs import db
from jobs.auth import audit, passwords
from jobs.auth.roles import Role
from jobs.models import utcnow
from jobs.settings import AuthMode, Settings
from jobs.web.models import WebSession
from tests.conftest import API_KEY
from tests.jobs.web.conftest import csrf_of, dashboard_app, sign_in, signin_form


def test_a_page_without_a_session_sends_the_browser_to_sign_in(dashboard: TestClient) -> None:
    answer = dashboard.get("/jobs")

    assert answer.status_code == 303
    assert answer.headers["location"] == "/signin?next=/jobs"


def test_no_other_sites_page_may_frame_the_sign_in_or_any_page(dashboard: TestClient) -> None:
    # A page laid over a framed dashboard would have its buttons clicked unknowingly.
    for answer in (dashboard.get("/signin"), dashboard.get("/jobs")):
        assert answer.headers["x-frame-options"] == "DENY"
        assert answer.headers["content-security-policy"] == "frame-ancestors 'none'"
        assert answer.headers["x-content-type-options"] == "nosniff"


def test_the_sign_in_leads_back_to_the_page_with_its_query_or_to_the_page_a_form_was_on(
        dashboard: TestClient) -> None:
    page = dashboard.get("/backups/diff?first=3&machine=1016", follow_redirects=False)
    form = dashboard.post("/m/1016/mkdir", data={"name": "X"}, follow_redirects=False,
                          headers={"referer": "http://testserver/m/1016?dir=%2F%2FCNC_MEM%2F"})
    elsewhere = dashboard.post("/m/1016/mkdir", data={"name": "X"}, follow_redirects=False,
                               headers={"referer": "http://example.org/m/1016"})

    assert page.headers["location"] == "/signin?next=/backups/diff%3Ffirst%3D3%26machine%3D1016"
    assert form.headers["location"] == "/signin?next=/m/1016%3Fdir%3D%252F%252FCNC_MEM%252F"
    assert elsewhere.headers["location"] == "/signin?next=/"


def test_the_sign_in_leads_back_to_the_page_without_the_key_its_address_held(
        dashboard: TestClient) -> None:
    # The key would stay in the browser's address bar and history past the sign-in.
    keyed = dashboard.get("/backups?apikey=test-key-0123456789", follow_redirects=False)
    among = dashboard.get("/backups/diff?first=3&APIKEY=k1&machine=1016&api%6Bey=k2",
                          follow_redirects=False)

    assert keyed.headers["location"] == "/signin?next=/backups"
    assert among.headers["location"] == "/signin?next=/backups/diff%3Ffirst%3D3%26machine%3D1016"


def test_signed_in_pages_are_never_kept_by_the_browser(admin) -> None:
    client, _ = admin

    for path in ("/", "/jobs", "/m/1016", "/schedules"):
        assert client.get(path).headers.get("cache-control") == "no-store", path


def test_a_wrong_password_is_refused_with_the_words_a_wrong_name_gets(
        dashboard: TestClient) -> None:
    wrong_password = signin_form(dashboard, name="admin", password="nope")
    wrong_name = signin_form(dashboard, name="nobody", password="nope")

    assert wrong_password.status_code == wrong_name.status_code == 200  # the form, again
    assert "wrong name or password" in wrong_password.text
    assert "wrong name or password" in wrong_name.text
    assert "dncq_session" not in wrong_password.headers.get("set-cookie", "")


def test_signing_in_sets_an_httponly_same_site_strict_cookie(dashboard: TestClient) -> None:
    cookie = signin_form(dashboard, name="admin", password="test-key-0123456789"
                         ).headers["set-cookie"]
    assert cookie.startswith("dncq_session=")
    assert "HttpOnly" in cookie and "SameSite=strict" in cookie


def test_a_sign_in_sent_from_another_sites_page_is_refused_and_signs_nobody_in(
        settings: Settings) -> None:
    app = dashboard_app(settings)
    with TestClient(app, follow_redirects=False) as attacker, \
            TestClient(app, follow_redirects=False) as victim:
        # The other site's page carries a token of the sign-in form, fetched by its owner.
        token = csrf_of(attacker.get("/signin").text)
        fields = {"name": "admin", "password": "test-key-0123456789", "next": "/"}

        forged = victim.post("/signin", data={"csrf_token": token, **fields})
        bare = victim.post("/signin", data=fields)

        assert forged.status_code == bare.status_code == 403
        assert "CSRF token is missing or wrong" in forged.text
        assert "dncq_session" not in victim.cookies
        assert victim.get("/jobs").status_code == 303  # to the sign-in page


def test_the_sign_in_form_sent_from_its_own_page_signs_in(dashboard: TestClient) -> None:
    answer = signin_form(dashboard, name="admin", password="test-key-0123456789", next="/")

    assert answer.status_code == 303 and answer.headers["location"] == "/"
    assert dashboard.get("/jobs").status_code == 200


def test_the_database_keeps_only_a_hash_of_the_cookie(dashboard: TestClient,
                                                      settings: Settings) -> None:
    sign_in(dashboard)
    token = dashboard.cookies["dncq_session"]

    with db.session_scope(settings.resolved_database_url) as session:
        [row] = session.query(WebSession).all()
        assert row.token_hash != token and token not in row.token_hash
        assert row.user_name == "admin"


def test_signing_in_leads_to_the_page_asked_for_but_never_to_another_site(
        dashboard: TestClient) -> None:
    asked = signin_form(dashboard, name="admin", password="test-key-0123456789",
                        next="/backups")
    elsewhere = signin_form(dashboard, name="admin", password="test-key-0123456789",
                            next="//evil.example/")

    assert asked.headers["location"] == "/backups"
    assert elsewhere.headers["location"] == "/"


def test_signing_out_ends_the_session(dashboard: TestClient) -> None:
    csrf = sign_in(dashboard)
    token = dashboard.cookies["dncq_session"]

    answer = dashboard.post("/signout", data={"csrf_token": csrf})

    assert answer.status_code == 303 and answer.headers["location"] == "/signin"
    dashboard.cookies.set("dncq_session", token)  # the old cookie, kept by a thief
    assert dashboard.get("/").status_code == 303


def test_a_post_without_the_csrf_token_is_refused_with_403(admin) -> None:
    client, _ = admin

    answer = client.post("/jobs/nosuchjob/retry")

    assert answer.status_code == 403
    assert "CSRF" in answer.text
    assert answer.text.count("its CSRF token is missing or wrong") == 1  # said once


def test_a_post_with_another_sessions_csrf_token_is_refused_with_403(
        admin, settings: Settings) -> None:
    client, _ = admin
    other = TestClient(client.app, follow_redirects=False)
    theirs = sign_in(other)

    answer = client.post("/signout", data={"csrf_token": theirs})

    assert answer.status_code == 403


def test_the_csrf_token_may_come_as_a_header(admin) -> None:
    client, csrf = admin

    answer = client.post("/check", headers={"X-CSRF-Token": csrf})

    assert answer.status_code == 303


def test_a_session_unused_longer_than_the_idle_time_has_ended(
        admin, settings: Settings) -> None:
    client, _ = admin
    with db.session_scope(settings.resolved_database_url) as session:
        row = session.query(WebSession).one()
        row.last_seen_at = utcnow() - timedelta(seconds=settings.web_session_idle_s + 1)

    assert client.get("/").status_code == 303
    with db.session_scope(settings.resolved_database_url) as session:
        assert session.query(WebSession).count() == 0


def test_a_session_ends_at_its_maximum_age_however_much_it_is_used(
        admin, settings: Settings) -> None:
    client, _ = admin
    with db.session_scope(settings.resolved_database_url) as session:
        session.query(WebSession).one().expires_at = utcnow() - timedelta(seconds=1)

    assert client.get("/").status_code == 303


def test_the_api_still_wants_its_key_beside_the_dashboard(admin) -> None:
    client, _ = admin  # a signed-in browser is not an API client

    assert client.get("/api/jobs").status_code == 401
    assert client.get("/api/jobs", headers={"X-Api-Key": "test-key-0123456789"}
                      ).status_code == 200


def test_with_authentication_off_a_browser_is_an_anonymous_admin_without_signing_in(
        settings: Settings) -> None:
    open_settings = settings.model_copy(update={"auth": AuthMode.NONE, "api_key": None})
    with TestClient(dashboard_app(open_settings)) as client:
        page = client.get("/admin/users")

    assert page.status_code == 200
    assert "anonymous" in page.text


def test_a_sign_in_removes_the_sessions_nobody_came_back_to(
        dashboard: TestClient, settings: Settings) -> None:
    sign_in(dashboard)
    with db.session_scope(settings.resolved_database_url) as session:
        session.query(WebSession).one().expires_at = utcnow() - timedelta(seconds=1)

    sign_in(TestClient(dashboard.app, follow_redirects=False))

    with db.session_scope(settings.resolved_database_url) as session:
        assert session.query(WebSession).count() == 1


def _stream_until_signed_out(settings: Settings, add_machines, monkeypatch,
                             end_session) -> list[str]:
    """The lines of a job page's live stream, read while `end_session` ends the session."""
    import httpx

    from jobs.web import deps
    from tests.conftest import API_KEY
    from tests.live_server import HTTP_TIMEOUT_S, serving

    monkeypatch.setattr(deps, "SESSION_RECHECK_S", 0.2)
    add_machines({"id": "m0", "name": "M0", "model": "Mock"})
    lines: list[str] = []
    with serving(dashboard_app(settings)) as server, \
            httpx.Client(base_url=server.url, timeout=HTTP_TIMEOUT_S) as browser:
        job = browser.post("/api/jobs", headers={"X-Api-Key": API_KEY}, json={
            "kind": "delete", "targets": [{"machineID": "m0", "fileName": "A.nc"}]}).json()
        signin_form(browser, name="admin", password=API_KEY, next="/")
        with browser.stream("GET", f"/jobs/{job['id']}/events") as events:
            for line in events.iter_lines():
                lines.append(line)
                if line.startswith("data: {\"id\""):
                    end_session(settings)  # nobody runs the job: it stays pending
                if line == "event: signedout":
                    break
    return lines


def test_a_live_stream_ends_when_its_session_expires(settings: Settings, add_machines,
                                                     monkeypatch) -> None:
    def expire(settings: Settings) -> None:
        with db.session_scope(settings.resolved_database_url) as session:
            session.query(WebSession).one().expires_at = utcnow() - timedelta(seconds=1)

    lines = _stream_until_signed_out(settings, add_machines, monkeypatch, expire)

    assert lines[-1] == "event: signedout"
    assert any(line.startswith("data: {\"id\"") for line in lines)


def test_a_live_stream_ends_when_its_session_is_ended_elsewhere(settings: Settings, add_machines,
                                                      monkeypatch) -> None:
    def sign_out_everywhere(settings: Settings) -> None:
        with db.session_scope(settings.resolved_database_url) as session:
            session.query(WebSession).delete()

    assert _stream_until_signed_out(settings, add_machines, monkeypatch,
                                    sign_out_everywhere)[-1] == "event: signedout"


def test_the_admin_key_sign_in_is_locked_out_after_as_many_failures_as_a_users(
        dashboard: TestClient, settings: Settings) -> None:
    for _ in range(settings.signin_max_failures):
        signin_form(dashboard, name="admin", password="a guess at the key")

    answer = signin_form(dashboard, name="admin", password=API_KEY)

    assert answer.status_code == 200  # the form again, no session
    assert "wrong name or password, or too many failed sign-ins" in answer.text
    assert "dncq_session" not in answer.headers.get("set-cookie", "")


def test_wrong_guesses_at_the_admin_key_from_one_address_lock_out_that_address_alone(
        settings: Settings) -> None:
    """The key opens the API too, where no guess is counted: a lock-out of `admin` for
    everyone would only let anyone keep the administrator out of the dashboard."""
    app = dashboard_app(settings)
    with TestClient(app, follow_redirects=False, client=("203.0.113.9", 40000)) as guesser, \
            TestClient(app, follow_redirects=False, client=("10.0.0.7", 40000)) as admin:
        for _ in range(settings.signin_max_failures):
            signin_form(guesser, name="admin", password="a guess at the key")

        assert signin_form(guesser, name="admin", password=API_KEY).status_code == 200
        assert signin_form(admin, name="admin", password=API_KEY).status_code == 303


def test_an_admin_ends_an_address_lock_out_of_the_admin_sign_in_through_the_api(
        settings: Settings) -> None:
    app = dashboard_app(settings)
    with TestClient(app, follow_redirects=False, client=("203.0.113.9", 40000)) as locked, \
            TestClient(app, follow_redirects=False, client=("10.0.0.7", 40000)) as admin:
        for _ in range(settings.signin_max_failures):
            signin_form(locked, name="admin", password="a stale copy of the key")
        listed = admin.get("/api/lockouts", headers={"X-Api-Key": API_KEY}).json()

        ended = admin.delete("/api/lockouts/203.0.113.9", headers={"X-Api-Key": API_KEY})

        assert [(e["address"], e["counted"]) for e in listed] == [
            ("203.0.113.9", "admin sign-ins")]
        assert listed[0]["lockedUntil"] is not None
        assert ended.status_code == 200
        assert [e["counted"] for e in ended.json()["ended"]] == ["admin sign-ins"]
        assert signin_form(locked, name="admin", password=API_KEY).status_code == 303
        assert admin.get("/api/lockouts", headers={"X-Api-Key": API_KEY}).json() == []


def test_wrong_guesses_at_the_admin_key_from_one_ipv6_host_add_up_over_its_addresses(
        settings: Settings) -> None:
    """A host is given a whole /64: a new address in it for each guess wins it no more."""
    app = dashboard_app(settings)
    for n in range(settings.signin_max_failures):
        with TestClient(app, follow_redirects=False,
                        client=(f"2001:db8:7:1::{n + 1:x}", 40000)) as guesser:
            signin_form(guesser, name="admin", password="a guess at the key")

    with TestClient(app, follow_redirects=False, client=("2001:db8:7:1::ff", 40000)) as same, \
            TestClient(app, follow_redirects=False, client=("2001:db8:7:2::1", 40000)) as other:
        assert signin_form(same, name="admin", password=API_KEY).status_code == 200
        assert signin_form(other, name="admin", password=API_KEY).status_code == 303


def test_a_stored_users_lock_out_holds_from_every_address(
        settings: Settings, users: Callable[..., None]) -> None:
    """A password may be guessable: its failures are the user's, wherever they come from."""
    users("alice", Role.VIEWER, password="alice-password")
    app = dashboard_app(settings)
    with TestClient(app, follow_redirects=False, client=("203.0.113.9", 40000)) as guesser, \
            TestClient(app, follow_redirects=False, client=("10.0.0.7", 40000)) as alice:
        for _ in range(settings.signin_max_failures):
            signin_form(guesser, name="alice", password="a guess at hers")

        assert signin_form(alice, name="alice", password="alice-password").status_code == 200


def test_the_admin_key_signs_in_after_fewer_failures_and_starts_the_count_again(
        dashboard: TestClient, settings: Settings) -> None:
    for _ in range(settings.signin_max_failures - 1):
        signin_form(dashboard, name="admin", password="a guess at the key")
    sign_in(dashboard)
    for _ in range(settings.signin_max_failures - 1):
        signin_form(dashboard, name="admin", password="a guess at the key")

    assert signin_form(dashboard, name="admin", password=API_KEY).status_code == 303


class CountingHasher:
    """The argon2 hasher, counting its verifies: what makes a sign-in's time."""

    def __init__(self, hasher: PasswordHasher) -> None:
        self.hasher, self.verifies = hasher, 0

    def verify(self, *args: Any) -> Any:
        self.verifies += 1
        return self.hasher.verify(*args)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.hasher, name)


@pytest.mark.parametrize(("name", "password"), [
    ("admin", API_KEY), ("admin", "a guess at the key"), ("alice", "alice-password"),
    ("alice", "a guess at hers"), ("nobody", "a guess")])
def test_every_sign_in_costs_one_argon2_verify_so_its_time_tells_no_name_apart(
        dashboard: TestClient, users: Callable[..., None], monkeypatch: pytest.MonkeyPatch,
        name: str, password: str) -> None:
    # The admin key's `admin` was answered without one, tens of times sooner than any other
    # name: how long a sign-in as admin took said whether a user of that name is stored.
    users("alice", Role.VIEWER, password="alice-password")
    counting = CountingHasher(passwords._hasher)
    monkeypatch.setattr(passwords, "_hasher", counting)

    signin_form(dashboard, name=name, password=password)

    assert counting.verifies == 1


@pytest.mark.parametrize("name", ["admin", "alice"])  # the admin key's admin, a stored user
def test_a_lock_out_is_written_once_to_the_audit_trail_with_the_name_and_address(
        dashboard: TestClient, users: Callable[..., None], settings: Settings,
        name: str) -> None:
    users("alice", Role.VIEWER, password="alice-password")
    for _ in range(settings.signin_max_failures + 2):  # the last two refused while locked
        signin_form(dashboard, name=name, password="a guess at it")

    with db.session_scope(settings.resolved_database_url) as session:
        written = audit.list_events(session=session, action="lock out")
        [locked] = [(e.who, e.target, e.address, e.method, e.path, e.status, e.detail)
                    for e in written]

    until = locked[-1].pop("until")
    assert locked[:-1] == ("-", name, "testclient", "POST", "/signin", 401)
    assert locked[-1] == {"failures": settings.signin_max_failures}
    assert datetime.fromisoformat(until) > utcnow()
