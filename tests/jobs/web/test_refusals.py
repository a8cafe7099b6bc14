"""The dashboard's refusals in the audit trail: each under its form's action, once, with the
status the API answers the same refusal with."""

from __future__ import annotations

from collections.abc import Callable

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from jobs import db
from jobs.auth import audit
from jobs.auth import service as auth
from jobs.fleet import registry
from jobs.models import Job
from jobs.requests import demo
from jobs.settings import Settings
from jobs.web.principal import Role
from tests.conftest import API_KEY
from tests.jobs.web.conftest import dashboard_app, sign_in

KEY = {"X-Api-Key": API_KEY}


def _written(settings: Settings, path: str) -> list[tuple[str, str, int, str | None]]:
    """Who, action, status and target of each entry of the dashboard's `path`, oldest first."""
    with db.session_scope(settings.resolved_database_url) as session:
        return [(e.who, e.action, e.status, e.target)
                for e in reversed(audit.list_events(session=session)) if e.path == path]


@pytest.fixture
def filled_library(demo_fleet: None, settings: Settings) -> None:
    """The demo fleet and its library programs."""
    with db.session_scope(settings.resolved_database_url) as session:
        demo.seed(session=session, settings=settings)


@pytest.fixture
def vera(settings: Settings, users: Callable[..., None]) -> tuple[TestClient, str]:
    """The dashboard signed in as vera, a viewer, and her CSRF token."""
    users("vera", Role.VIEWER)
    client = TestClient(dashboard_app(settings), follow_redirects=False)
    return client, sign_in(client, "vera", "secret-password")


def test_a_form_refused_for_the_role_is_recorded_under_the_forms_action(
        vera: tuple[TestClient, str], settings: Settings) -> None:
    # It was `dashboard make folder`, where the folders the form makes are `make folder`.
    client, csrf = vera

    answer = client.post("/m/1016/mkdir", data={"csrf_token": csrf, "name": "X"})

    assert answer.status_code == 403
    assert _written(settings, "/m/1016/mkdir") == [("vera", "make folder", 403, "1016")]


@pytest.mark.parametrize("decision", ["approve", "reject"])
def test_a_library_decision_refused_for_the_role_is_recorded_as_that_decision(
        vera: tuple[TestClient, str], settings: Settings, decision: str) -> None:
    client, csrf = vera
    path = "/library/p/VIPROS/0010/decide"

    answer = client.post(path, data={"csrf_token": csrf, "number": "1", "decision": decision})

    assert answer.status_code == 403
    assert _written(settings, path) == [
        ("vera", f"{decision} library version", 403, "VIPROS/0010")]


def test_a_form_sent_twice_is_recorded_under_the_forms_action(
        demo_fleet: None, admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin
    form = {"csrf_token": csrf, "source": "upload", "action": "start", "ids": ["1011"],
            "file_name": "NEW.MPF", "form_key": "k" * 32}
    upload = {"upload": ("NEW.MPF", b"G0 X0\nM30\n")}

    first = client.post("/rollout", data=form, files=upload)
    second = client.post("/rollout", data=form, files=upload)

    assert (first.status_code, second.status_code) == (303, 409)
    job = first.headers["location"].rsplit("/", 1)[1]
    assert _written(settings, "/rollout") == [("admin", "start rollout", 200, job),
                                              ("admin", "start rollout", 409, None)]


def test_a_sign_in_without_its_token_is_recorded_as_a_sign_in(
        dashboard: TestClient, settings: Settings) -> None:
    answer = dashboard.post("/signin", data={"name": "admin", "password": "x", "next": "/"})

    assert answer.status_code == 403
    assert _written(settings, "/signin") == [("-", "sign in", 403, None)]


# A user page's own check, the user it is on, its action, and the API's request refused
# alike (None: the API has no such check; a value refused is 422 there).
OWN_CHECKS = {
    "a role that is none": ("/admin/users/anna/set", {"role": "boss"}, "anna", "change user",
                            ("PATCH", "/api/users/anna", {"role": "boss"})),
    "a new user's role that is none": (
        "/admin/users", {"name": "bo", "role": "boss", "password": "secret-password",
                         "password_again": "secret-password"}, "bo", "add user",
        ("POST", "/api/users", {"name": "bo", "role": "boss", "password": "secret-password"})),
    "a key's role that is none": ("/admin/keys", {"name": "k1", "role": "boss"}, "k1",
                                  "add key", ("POST", "/api/keys", {"name": "k1",
                                                                    "role": "boss"})),
    "passwords that differ": ("/admin/users/anna/password",
                              {"password": "secret-password", "password_again": "other-one"},
                              "anna", "set password", None),
    "demoting yourself": ("/admin/users/admin/set", {"role": "viewer"}, "admin", "change user",
                          None),
    "disabling yourself": ("/admin/users/admin/disable", {}, "admin", "disable user", None),
    "removing yourself": ("/admin/users/admin/delete", {}, "admin", "delete user", None),
}


@pytest.mark.parametrize("case", OWN_CHECKS)
def test_a_user_page_refusing_a_change_itself_records_it_with_the_apis_status(
        admin: tuple[TestClient, str], settings: Settings, users: Callable[..., None],
        case: str) -> None:
    # These left no entry, where the same refusal by the service is recorded.
    page, form, name, action, api = OWN_CHECKS[case]
    users("anna", Role.VIEWER)
    client, csrf = admin
    status = 422
    if api is not None:
        method, path, body = api
        status = client.request(method, path, headers=KEY, json=body).status_code

    answer = client.post(page, data={"csrf_token": csrf, **form})

    assert answer.status_code in (200, 303)  # the page again, saying why
    assert status == (400 if "role" in case else 422)
    assert _written(settings, page) == [("admin", action, status, name)]
    with db.session_scope(settings.resolved_database_url) as session:
        assert {u.name: (u.role, u.disabled) for u in auth.list_users(session=session)} == {
            "anna": (Role.VIEWER, False)}  # nothing changed, nothing added
        assert auth.list_keys(session=session) == []


UPLOAD = {"upload": ("NEW.MPF", b"G0 X0\nM30\n")}
# A rollout started on the dashboard and refused, and the job API's request refused alike.
ROLLOUT_REFUSALS = {
    "no program": ({"source": "upload", "ids": ["1011"]}, None,
                   {"machines": {"ids": ["1011"]}, "fileName": "A.NC"}),
    "a library version nobody has": (
        {"source": "library", "library": "VIPROS/0010 v99", "ids": ["1011"]}, None,
        {"machines": {"ids": ["1011"]}, "library": "VIPROS/0010 v99"}),
    "an option that is no number": (
        {"source": "upload", "ids": ["1011"], "abort_after_failures": "x"}, UPLOAD,
        {"machines": {"ids": ["1011"]}, "fileName": "A.NC", "content": "x",
         "abort_after_failures": "x"}),
    "machines nobody has": ({"source": "upload", "ids": ["9999"]}, UPLOAD,
                            {"machines": {"ids": ["9999"]}, "fileName": "A.NC",
                             "content": "x"}),
}


@pytest.mark.parametrize("case", ROLLOUT_REFUSALS)
def test_a_rollout_refused_on_start_is_recorded_with_the_job_apis_status(
        filled_library: None, admin: tuple[TestClient, str], settings: Settings,
        case: str) -> None:
    # These left no entry, where the API records its refusal of the same job.
    form, files, api_body = ROLLOUT_REFUSALS[case]
    client, csrf = admin
    by_api = client.post("/api/jobs", headers=KEY, json={"kind": "send", **api_body})

    answer = client.post("/rollout", data={"csrf_token": csrf, "action": "start", **form},
                         files=files)

    assert by_api.status_code in (400, 404, 422), by_api.text
    assert answer.status_code in (200, 422)  # the form again, saying why
    assert _written(settings, "/rollout") == [("admin", "start rollout", by_api.status_code,
                                               None)]
    with db.session_scope(settings.resolved_database_url) as session:
        assert session.scalars(select(Job)).all() == []


def test_a_rollout_of_no_machine_is_recorded_as_refused_whole(
        filled_library: None, admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin

    previewed = client.post("/rollout", data={"csrf_token": csrf, "action": "preview",
                                              "source": "upload"}, files=UPLOAD)
    started = client.post("/rollout", data={"csrf_token": csrf, "action": "start",
                                            "source": "upload"}, files=UPLOAD)

    assert (previewed.status_code, started.status_code) == (422, 422)
    assert "no machine selected" in started.text
    assert _written(settings, "/rollout") == [("admin", "start rollout", 422, None)]


def test_a_machine_checked_from_the_dashboard_is_in_the_audit_trail_as_the_apis_check_is(
        demo_fleet: None, vera: tuple[TestClient, str], settings: Settings) -> None:
    # The API records every check (machines.check); the dashboard's left no entry.
    client, csrf = vera
    by_api = client.post("/api/machines/check", headers=KEY, json={"ids": ["1010"]})

    machine = client.post("/m/1010/check", data={"csrf_token": csrf})
    fleet = client.post("/check", data={"csrf_token": csrf})

    assert (by_api.status_code, machine.status_code, fleet.status_code) == (200, 303, 303)
    with db.session_scope(settings.resolved_database_url) as session:
        written = {e.action: (e.who, e.status, e.target, e.detail)
                   for e in audit.list_events(session=session, action=None)}
        machines = len(registry.list_all(session=session))
    assert written["machines.check"][1] == 200
    assert written["check machine"] == ("vera", 200, "1010", None)
    assert written["check fleet"] == ("vera", 200, None, {"machines": machines})
