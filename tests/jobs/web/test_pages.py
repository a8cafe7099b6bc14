"""The dashboard's pages, server side: each renders, and each role sees and may do its own."""

from __future__ import annotations

import html
import json
import re
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from typing import Any

import pytest
from fastapi.testclient import TestClient

from jobs import db
from jobs.auth import audit
from jobs.backup_models import BackupStatus
from jobs.inbox import service as inbox
from jobs.library import service as library
from jobs.library.models import VersionState
from jobs.models import Job
from jobs.requests import demo
from jobs.settings import Settings
from jobs.web.principal import Role
from tests.conftest import API_KEY
from tests.jobs.helpers import mock_file, run_backup
from tests.jobs.web.conftest import csrf_of, dashboard_app, sign_in

KEY = {"X-Api-Key": API_KEY}
PROGRAM = b"%\nO0077 (BRACKET)\nG21 G90\nT01 M06\nM30\n%\n"


def _received(settings: Settings, data: bytes = PROGRAM) -> int:
    with db.session_scope(settings.resolved_database_url) as session:
        return inbox.receive(session=session, settings=settings, machine_id="1010", data=data,
                             name="0077", folder="VIPROS").id


def _a_job(client: TestClient, csrf: str) -> str:
    answer = client.post("/rollout", data={
        "csrf_token": csrf, "source": "upload", "action": "start", "ids": ["1011"],
        "file_name": "NEW.MPF"}, files={"upload": ("NEW.MPF", b"G0 X0\nM30\n")})
    assert answer.status_code == 303, answer.text
    return answer.headers["location"].rsplit("/", 1)[1]


def _a_run(client: TestClient) -> int:
    program = client.post("/api/programs", content=b"G0 X0\nM30\n", headers={
        **KEY, "content-type": "application/octet-stream"}).json()
    job = client.post("/api/jobs", headers=KEY, json={
        "kind": "dnc_run", "machines": {"ids": ["2001"]}, "program": program["id"],
        "fileName": "PART.NC"}).json()
    return int(client.get(f"/api/jobs/{job['id']}", headers=KEY).json()["runs"][0]["id"])


@pytest.fixture
def filled(demo_fleet: None, admin: tuple[TestClient, str], settings: Settings
           ) -> dict[str, Any]:
    """A demo fleet with a job, a run, an inbox item and a library program to show."""
    client, csrf = admin
    with db.session_scope(settings.resolved_database_url) as session:
        demo.seed(session=session, settings=settings)
    return {"job": _a_job(client, csrf), "run": _a_run(client), "item": _received(settings)}


PAGES = ["/", "/?view=table", "/?tag=mills", "/?state=unchecked&q=lathe", "/m/1010",
         "/m/1011?dir=dir1", "/m/1016", "/jobs", "/jobs?state=queued&kind=send",
         "/jobs?machine=1014", "/jobs/{job}",
         "/rollout", "/backups", "/backups?day=2026-12-01", "/inbox", "/inbox?state=",
         "/inbox/{item}", "/runs", "/runs/{run}", "/library", "/library?folder=VIPROS",
         "/library/p/VIPROS/0010", "/library/p/VIPROS/0010?old=1&new=1", "/schedules",
         "/admin/users", "/admin/audit", "/admin/audit?who=admin&action=start+rollout"]


@pytest.mark.parametrize("path", PAGES)
def test_every_page_renders_for_an_admin_with_the_demo_fleet(
        filled: dict[str, Any], admin: tuple[TestClient, str], path: str) -> None:
    client, _ = admin

    answer = client.get(path.format(**filled))

    assert answer.status_code == 200, answer.text[-2000:]
    assert "<main>" in answer.text and "Sign out" in answer.text


@pytest.fixture
def in_berlin(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """The server's clock in Berlin (CET in winter, CEST in summer)."""
    monkeypatch.setenv("TZ", "Europe/Berlin")
    time.tzset()
    yield
    monkeypatch.undo()
    time.tzset()


# A time as a page says it, its tags taken away: date, clock, and what follows the clock.
TIME_SAID = re.compile(r"\d{4}-\d\d-\d\d \d\d:\d\d(?::\d\d)?( [^\s<]+)?")


def _text(page: str) -> str:
    """A page's text: the tags inside a line taken away, the others ending a line."""
    inline = re.sub(r"</?(span|time|a|wbr|strong)\b[^>]*>", "", page)
    return html.unescape(re.sub(r"<[^>]+>", "\n", inline))


def test_every_time_on_every_page_names_its_zone(
        filled: dict[str, Any], admin: tuple[TestClient, str], in_berlin: None) -> None:
    # The pages showed the server's clock bare (2026-12-06 03:40:12), where the CLI says CET.
    client, _ = admin
    client.post("/api/schedules", headers=KEY, json={
        "name": "nightly", "cron": "0 2 * * *", "timezone": "Europe/Berlin",
        "machines": {"all": True}})
    zones = []
    for path in PAGES:
        page = client.get(path.format(**filled)).text
        zones += [(path, zone) for zone in TIME_SAID.findall(_text(page))]

    assert {path for path, _ in zones} >= {"/jobs", "/inbox", "/library", "/schedules",
                                           "/admin/audit"}
    assert {(path, zone) for path, zone in zones
            if zone not in (" CET", " CEST", " UTC", " Europe/Berlin")} == set()


def test_two_jobs_an_hour_apart_in_the_hour_the_clocks_repeat_read_apart(
        demo_fleet: None, admin: tuple[TestClient, str], settings: Settings,
        in_berlin: None) -> None:
    # Berlin, 25 October 2026: 00:30 and 01:30 UTC both read 02:30, the clocks gone back.
    client, csrf = admin
    made = [_a_job(client, csrf) for _ in range(2)]
    with db.session_scope(settings.resolved_database_url) as session:
        for job_id, hour in zip(made, (0, 1), strict=True):
            session.get_one(Job, job_id).created_at = datetime(2026, 10, 25, hour, 30,
                                                                tzinfo=UTC)

    page = client.get("/jobs").text

    assert ('<time class="when" datetime="2026-10-25T01:30:00+00:00"><span>2026-10-25</span> '
            '<span>02:30 CET</span></time>') in page
    assert ('<time class="when" datetime="2026-10-25T00:30:00+00:00"><span>2026-10-25</span> '
            '<span>02:30 CEST</span></time>') in page


def test_the_jobs_dates_are_the_days_of_the_servers_clock_the_list_shows(
        demo_fleet: None, admin: tuple[TestClient, str], settings: Settings,
        in_berlin: None) -> None:
    # Made 2026-12-06 00:30 CET (23:30 UTC the day before): listed under the 6th, as shown.
    client, csrf = admin
    job_id = _a_job(client, csrf)
    with db.session_scope(settings.resolved_database_url) as session:
        session.get_one(Job, job_id).created_at = datetime(2026, 12, 5, 23, 30, tzinfo=UTC)

    on_the_6th = client.get("/jobs", params={"since": "2026-12-06", "until": "2026-12-07"})
    before_the_6th = client.get("/jobs", params={"until": "2026-12-06"})

    assert f'href="/jobs/{job_id}"' in on_the_6th.text
    assert "<span>2026-12-06</span> <span>00:30 CET</span>" in on_the_6th.text
    assert f'href="/jobs/{job_id}"' not in before_the_6th.text


@pytest.mark.parametrize("path", ["/jobs", "/runs", "/inbox", "/backups"])
def test_a_list_filtered_by_a_mistyped_machine_says_the_machine_meant(
        demo_fleet: None, admin: tuple[TestClient, str], path: str) -> None:
    client, _ = admin

    page = client.get(path, params={"machine": "1O10"})  # a letter O for the 0

    assert page.status_code == 404
    assert "10003 Invalid MachineID (1O10) (did you mean 1010?)" in html.unescape(page.text)


DESTRUCTIVE = re.compile(r'action="[^"]*/(delete|upload|mkdir|retry|cancel|approve|reject|'
                         r'restore|restore-replaced|stop|decide|run)"')


@pytest.fixture
def viewer(filled: dict[str, Any], users, settings: Settings) -> TestClient:
    users("vera", Role.VIEWER)
    client = TestClient(dashboard_app(settings), follow_redirects=False)
    sign_in(client, "vera", "secret-password")
    return client


@pytest.mark.parametrize("path", [p for p in PAGES if not p.startswith("/admin")])
def test_a_viewer_sees_no_destructive_control(
        viewer: TestClient, filled: dict[str, Any], path: str) -> None:
    page = viewer.get(path.format(**filled))

    assert page.status_code == 200
    assert not DESTRUCTIVE.search(page.text), DESTRUCTIVE.search(page.text)


def test_a_viewer_may_not_open_the_users_page(viewer: TestClient) -> None:
    assert viewer.get("/admin/users").status_code == 403


@pytest.mark.parametrize("path", [
    "/m/1010/delete", "/m/1010/mkdir", "/m/1010/upload", "/jobs/{job}/retry",
    "/jobs/{job}/cancel", "/jobs/{job}/restore-replaced", "/rollout",
    "/inbox/{item}/approve", "/inbox/{item}/reject", "/runs/{run}/stop",
    "/library/p/VIPROS/0010/decide", "/schedules/nightly/run", "/backups/none/restore"])
def test_a_viewers_state_changing_request_is_refused_with_403_even_with_its_token(
        viewer: TestClient, filled: dict[str, Any], settings: Settings, path: str) -> None:
    csrf = csrf_of(viewer.get("/").text)

    answer = viewer.post(path.format(**filled), data={
        "csrf_token": csrf, "name": "O1234", "number": "1", "decision": "approve",
        "machine": "1010"})

    assert answer.status_code == 403, answer.text
    assert "you (vera) are a viewer" in answer.text
    with db.session_scope(settings.resolved_database_url) as session:
        assert inbox.get(session=session, item_id=filled["item"]).state.value == "pending"


@pytest.mark.parametrize(("machine", "named"), [
    ("1010", "1010"), ("10%0A10", "'10\\n10'")])  # a control character is shown escaped
def test_an_operator_limited_to_some_machines_may_not_delete_on_others(
        filled: dict[str, Any], users, settings: Settings, machine: str, named: str) -> None:
    users("otto", Role.OPERATOR, machines=("1011",))
    client = TestClient(dashboard_app(settings), follow_redirects=False)
    csrf = sign_in(client, "otto", "secret-password")

    answer = client.post(f"/m/{machine}/delete", data={"csrf_token": csrf, "name": "1234"})

    assert answer.status_code == 403
    assert f"you (otto) may not change machine {named}; your machines: 1011" in \
        html.unescape(answer.text)


def test_an_operator_restores_a_backup_onto_its_machine_from_the_dashboard(
        demo_fleet: None, queue_client: TestClient, users, queue_settings: Settings) -> None:
    """As the API lets it (`POST /api/backups/{id}/restore` needs the operator role)."""
    backup = run_backup(queue_client, machines={"ids": ["1016"]})
    users("otto", Role.OPERATOR, machines=("1016",))
    client = TestClient(dashboard_app(queue_settings), follow_redirects=False)
    csrf = sign_in(client, "otto", "secret-password")

    page = client.get(f"/backups/{backup['id']}").text
    answer = client.post(f"/backups/{backup['id']}/restore",
                         data={"csrf_token": csrf, "machine": "1016", "path": "/1"})

    assert "Restore all of 1016" in page and "Restore this folder" in page
    assert answer.status_code == 303, answer.text
    job = queue_client.get(answer.headers["location"].replace("/jobs/", "/api/jobs/")).json()
    assert job["kind"] == "restore"


def test_a_run_stopped_from_the_dashboard_shows_on_the_jobs_pages_who_stopped_it(
        filled: dict[str, Any], dashboard: TestClient, users, settings: Settings) -> None:
    # Its job showed `cancelled` alone, as a job cancelled by anyone for any reason.
    run_job = dashboard.get(f"/api/runs/{filled['run']}", headers=KEY).json()["jobId"]
    users("otto", Role.OPERATOR)
    client = TestClient(dashboard_app(settings), follow_redirects=False)
    csrf = sign_in(client, "otto", "secret-password")

    client.post(f"/jobs/{run_job}/cancel", data={"csrf_token": csrf})

    shown = [re.sub(r"<[^>]+>", "", row) for row in
             client.get("/jobs").text.split("<tr>") if f"/jobs/{run_job}" in row]
    assert len(shown) == 1 and "cancelled stopped by otto" in " ".join(shown[0].split())
    assert "stopped by otto" in client.get(f"/jobs/{run_job}").text


def test_an_operator_stops_a_run_from_the_dashboard_and_may_not_cancel_a_rollout(
        filled: dict[str, Any], dashboard: TestClient, users, settings: Settings) -> None:
    """As the API lets it (POST /api/jobs/{id}/cancel): a job's cancel needs the role that
    starts a job of its kind, the operator's for a drip-feed run."""
    run_job = dashboard.get(f"/api/runs/{filled['run']}", headers=KEY).json()["jobId"]
    users("otto", Role.OPERATOR)
    client = TestClient(dashboard_app(settings), follow_redirects=False)
    csrf = sign_in(client, "otto", "secret-password")

    page = client.get(f"/jobs/{run_job}").text
    stopped = client.post(f"/jobs/{run_job}/cancel", data={"csrf_token": csrf})
    refused = client.post(f"/jobs/{filled['job']}/cancel", data={"csrf_token": csrf})

    assert "Stop the run" in page
    assert stopped.status_code == 303, stopped.text
    assert dashboard.get(f"/api/runs/{filled['run']}", headers=KEY).json()["state"] == \
        "cancelled"
    assert refused.status_code == 403
    assert "cancelling a send job needs the programmer role; you (otto) are an operator" in \
        refused.text
    with db.session_scope(settings.resolved_database_url) as session:
        assert {t.state.value for t in session.get(Job, filled["job"]).targets} != {"cancelled"}


def test_a_backups_page_says_why_a_machine_failed_in_its_own_words_and_offers_no_empty_restore(
        demo_fleet: None, add_machines, queue_client: TestClient, users,
        queue_settings: Settings) -> None:
    # It said only "20004 Machine is offline." (the CLI's `backup show` says more), and
    # offered "Restore all of z9" for a machine of which the backup holds nothing.
    add_machines({"id": "z9", "name": "Off", "model": "Mock", "options": {"offline": True}})
    backup = run_backup(queue_client, machines={"ids": ["1016", "z9"]}, max_attempts=1)
    users("otto", Role.OPERATOR)
    client = TestClient(dashboard_app(queue_settings), follow_redirects=False)
    sign_in(client, "otto", "secret-password")

    page = html.unescape(client.get(f"/backups/{backup['id']}").text)

    assert "20004 Machine is offline. - machine is offline (simulated)" in page
    assert "Restore all of 1016" in page and "Restore all of z9" not in page


@pytest.fixture
def limited_programmer(filled: dict[str, Any], users, settings: Settings
                       ) -> tuple[TestClient, str]:
    """A programmer who may change machine 1010 alone, signed in; the filled job is 1011's."""
    users("pia", Role.PROGRAMMER, machines=("1010",))
    client = TestClient(dashboard_app(settings), follow_redirects=False)
    return client, sign_in(client, "pia", "secret-password")


@pytest.mark.parametrize(("path", "form"), [
    ("/jobs/{job}/retry", {}), ("/jobs/{job}/cancel", {}),
    ("/jobs/{job}/restore-replaced", {}),
    ("/rollout", {"source": "upload", "action": "start", "ids": ["1010", "1011"],
                  "file_name": "NEW2.MPF"}),
    ("/backups/any/restore", {"machine": "1011", "replace": "on"})])
def test_a_programmer_limited_to_some_machines_changes_no_other_from_the_dashboard(
        limited_programmer: tuple[TestClient, str], filled: dict[str, Any], settings: Settings,
        path: str, form: dict[str, Any]) -> None:
    client, csrf = limited_programmer
    with db.session_scope(settings.resolved_database_url) as session:
        jobs_before = session.query(Job).count()

    answer = client.post(path.format(**filled), data={"csrf_token": csrf, **form},
                         files={"upload": ("NEW2.MPF", b"G0 X1\nM30\n")})

    assert answer.status_code == 403, answer.text
    assert "you (pia) may not change machine 1011; your machines: 1010" in answer.text
    with db.session_scope(settings.resolved_database_url) as session:
        assert session.query(Job).count() == jobs_before
        assert {t.state.value for t in session.get(Job, filled["job"]).targets} != {"cancelled"}


def test_a_programmer_limited_to_some_machines_rolls_out_to_those(
        limited_programmer: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = limited_programmer

    answer = client.post("/rollout", data={
        "csrf_token": csrf, "source": "upload", "action": "start", "ids": ["1010"],
        "file_name": "NEW2.MPF"}, files={"upload": ("NEW2.MPF", b"G0 X1\nM30\n")})

    assert answer.status_code == 303, answer.text


def test_a_rollout_preview_says_what_each_machine_would_do_and_starts_nothing(
        demo_fleet: None, admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin

    page = client.post("/rollout", data={
        "csrf_token": csrf, "source": "upload", "action": "preview", "ids": ["1011", "1014"],
        "file_name": "PART1.MPF"}, files={"upload": ("PART1.MPF", b"G0 X0\nM30\n")})

    assert page.status_code == 200
    assert re.search(r'data-machine="1011">.*?would fail.*?142', page.text, re.S)
    assert re.search(r'data-machine="1014">.*?send as PART1.MPF', page.text, re.S)
    assert "Start the rollout" in page.text
    with db.session_scope(settings.resolved_database_url) as session:
        assert session.query(Job).count() == 0


@pytest.mark.parametrize(("field", "value", "said"), [
    ("deliver_within", "soon", "deliver_within: "),
    ("abort_after_failures", "0", "abort_after_failures: "),
    ("abort_after_failures", "two", "abort after failures: a whole number, not 'two'"),
])
def test_a_rollout_option_refused_says_which_and_why_in_plain_words(
        demo_fleet: None, admin: tuple[TestClient, str], field: str, value: str,
        said: str) -> None:
    client, csrf = admin

    page = client.post("/rollout", data={
        "csrf_token": csrf, "source": "upload", "action": "preview", "ids": ["1014"],
        "file_name": "P.NC", field: value}, files={"upload": ("P.NC", b"G0 X0\nM30\n")})

    assert page.status_code == 422
    assert said in html.unescape(page.text)
    assert "pydantic" not in page.text and "validation error for" not in page.text


def test_an_upload_previewed_is_kept_by_the_server_and_started_without_sending_it_again(
        demo_fleet: None, admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin
    data = b"G0 X0\n" + b"G1 X1 Y1 F100\n" * 100_000  # 1.4 MB
    form = {"csrf_token": csrf, "source": "upload", "ids": ["1014"], "file_name": "BIG.NC"}

    preview = client.post("/rollout", data={**form, "action": "preview"},
                          files={"upload": ("BIG.NC", data)})
    kept = re.search(r'name="upload_payload" value="([0-9a-f]{64})"', preview.text)
    assert kept and len(preview.text) < len(data) // 10  # an id, not the file
    started = client.post("/rollout", data={**form, "action": "start",
                                            "upload_payload": kept.group(1)})

    assert started.status_code == 303, started.text
    with db.session_scope(settings.resolved_database_url) as session:
        [job] = session.query(Job).all()
        assert job.payload_id == kept.group(1)


def test_an_upload_over_the_limit_is_a_page_with_the_way_back_and_the_api_keeps_its_json(
        demo_fleet: None, admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin
    too_much = b"G0\n" * (settings.max_json_body_bytes // 3 + 1)

    page = client.post("/m/1016/upload", data={"csrf_token": csrf},
                       files={"file": ("BIG.NC", too_much)},
                       headers={"accept": "text/html", "referer": "http://testserver/m/1016"})
    api = client.post("/api/cnc/sendFile", params={"machineID": "1016", "fileName": "B.NC"},
                      content=too_much, headers={**KEY, "accept": "text/html"})

    assert page.status_code == 413 and "text/html" in page.headers["content-type"]
    assert "larger than the dashboard takes" in page.text and 'href="/m/1016"' in page.text
    assert api.status_code == 413 and api.json()["errorCode"] == 20013


def test_the_rollout_page_chooses_no_library_program_for_the_user(
        filled: dict[str, Any], admin: tuple[TestClient, str]) -> None:
    client, csrf = admin

    page = client.get("/rollout").text
    unchosen = client.post("/rollout", data={"csrf_token": csrf, "source": "library",
                                             "library": "", "action": "preview",
                                             "ids": ["1016"]})

    assert re.search(r'<select name="library">\s*<option value="">choose a program', page)
    assert unchosen.status_code == 422 and "choose the library program to send" in unchosen.text


def test_a_replace_on_many_machines_starts_only_once_confirmed(
        demo_fleet: None, admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin
    form = {"csrf_token": csrf, "source": "upload", "action": "start", "all": "on",
            "replace": "on", "file_name": "P.NC"}
    upload = {"upload": ("P.NC", b"G0 X0\nM30\n")}

    unconfirmed = client.post("/rollout", data=form, files=upload)
    confirmed = client.post("/rollout", data={**form, "confirm": "on"}, files=upload)

    assert unconfirmed.status_code == 422 and "tick the confirmation" in unconfirmed.text
    assert confirmed.status_code == 303
    with db.session_scope(settings.resolved_database_url) as session:
        [job] = session.query(Job).all()
        assert job.created_by == "admin" and job.options["replace"] is True
        refused, started = audit.list_events(session=session, action="start rollout")[::-1]
    assert (started.status, started.target) == (200, job.id)
    assert started.detail["targets"] > 5  # FLEET_WIDE
    assert (refused.status, refused.detail) == (422, {"unconfirmed": started.detail["targets"]})


def test_a_rollout_of_a_library_program_records_the_version_it_sent(
        filled: dict[str, Any], admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin

    answer = client.post("/rollout", data={"csrf_token": csrf, "source": "library",
                                           "library": "VIPROS/0010", "action": "start",
                                           "ids": ["1016"]})

    job_id = answer.headers["location"].rsplit("/", 1)[1]
    with db.session_scope(settings.resolved_database_url) as session:
        job = session.get(Job, job_id)
        assert job is not None and job.file_name == "0010"
        sent = library.for_send(session=session, folder="VIPROS", name="0010", number=None)
        assert job.library_version_id == sent.id


def test_approving_an_inbox_item_makes_it_a_library_version_by_the_signed_in_user(
        filled: dict[str, Any], admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin

    answer = client.post(f"/inbox/{filled['item']}/approve", data={"csrf_token": csrf})

    assert answer.status_code == 303
    with db.session_scope(settings.resolved_database_url) as session:
        item = inbox.get(session=session, item_id=filled["item"])
        assert item.state.value == "approved" and item.decided_by == "admin"


def test_a_rejected_inbox_item_offers_approval_on_its_page_and_is_approved(
        filled: dict[str, Any], admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin
    client.post(f"/inbox/{filled['item']}/reject", data={"csrf_token": csrf, "reason": "no"})

    page = client.get(f"/inbox/{filled['item']}").text
    answer = client.post(f"/inbox/{filled['item']}/approve", data={"csrf_token": csrf})

    assert f'action="/inbox/{filled["item"]}/approve"' in page
    assert f'action="/inbox/{filled["item"]}/reject"' not in page
    assert answer.status_code == 303
    with db.session_scope(settings.resolved_database_url) as session:
        assert inbox.get(session=session, item_id=filled["item"]).state.value == "approved"


def test_a_file_uploaded_on_the_machine_page_is_on_the_machine(
        demo_fleet: None, admin: tuple[TestClient, str]) -> None:
    client, csrf = admin

    client.post("/m/1011/upload", data={"csrf_token": csrf},
                files={"file": ("NEWPART.MPF", b"G0 X1\nM30\n")})

    assert "NEWPART.MPF" in client.get("/m/1011").text
    listing = client.get("/api/cnc/readProgramList", params={"machineID": "1011"},
                         headers=KEY).json()
    assert "NEWPART.MPF" in listing["programs"]


def test_sizes_and_free_space_are_in_the_binary_units_they_are_counted_in(
        demo_fleet: None, admin: tuple[TestClient, str], settings: Settings) -> None:
    # Counted in 1,024s and labelled KB and GB, a disk's 81.2 GB free read 75.6 GB here
    # where dncq machines check said 75.6 GiB of the same machine.
    client, csrf = admin
    mock_file(settings, "1016", "HALF.NC", "x" * 1536)
    client.post("/m/1016/check", data={"csrf_token": csrf})

    page = client.get("/m/1016").text

    row = re.search(r'data-file="HALF.NC">.*?<td class="num">([^<]*)</td>', page, re.S)
    assert row is not None and row.group(1) == "1.5 KiB"
    assert re.search(r" · [0-9.]+ [KMGT]iB free", page), "free space in KiB, MiB or GiB"


def test_a_runs_live_rate_is_the_blocks_it_ran_from_its_start_line_as_dncq_run_says(
        demo_fleet: None, admin: tuple[TestClient, str], settings: Settings) -> None:
    # The page counted the lines sent (the header, and those the control held ahead of its
    # running line) as "lines/s", where dncq run showed the blocks run as "blocks/s".
    from datetime import UTC, datetime, timedelta

    from jobs.models import Run, RunState

    started = datetime(2026, 12, 1, 8, 0, tzinfo=UTC)
    with db.session_scope(settings.resolved_database_url) as session:
        run = Run(job_id="restarted", position=0, machine_id="2001", program_name="P.NC",
                  program_id="0" * 64, state=RunState.STOPPED, started_at=started,
                  ended_at=started + timedelta(seconds=10), start_line=501,
                  header=["G90"] * 12, lines_total=2012, lines_sent=712, last_line=1000)
        session.add(run)
        session.flush()
        run_id = run.id
    client, _ = admin

    events = client.get(f"/runs/{run_id}/events").text

    sent = [json.loads(line[len("data: "):]) for line in events.splitlines()
            if line.startswith("data: {") and '"rate"' in line]
    assert sent[-1]["rate"] == 50.0  # lines 501 to 1000 in 10 s


def test_a_file_deleted_on_the_machine_page_is_gone_from_the_machine(
        demo_fleet: None, admin: tuple[TestClient, str]) -> None:
    client, csrf = admin

    answer = client.post("/m/1011/delete", data={"csrf_token": csrf, "name": "PART1.MPF"})

    assert "Deleted" in client.get(answer.headers["location"]).text
    listing = client.get("/api/cnc/readProgramList", params={"machineID": "1011"},
                         headers=KEY).json()
    assert "PART1.MPF" not in listing["programs"]


def test_a_failed_targets_card_says_why_beside_its_code(admin: tuple[TestClient, str]
                                                       ) -> None:
    client, _ = admin
    sent = client.post("/api/cnc/batchSendFile", headers=KEY, json={
        "content": "G0\n", "targets": [{"machineID": "nope", "fileName": "P.nc"}]})

    page = client.get(f"/jobs/{sent.headers['X-Dncq-Job']}").text

    assert re.search(r"data-t-msg>10003 [^<]* \(Invalid MachineID \(nope\)\)<", page)
    assert "data-done>1 of 1 final<" in page  # before the live stream says it


def test_a_job_that_does_not_exist_is_a_page_that_says_so(admin: tuple[TestClient, str]
                                                          ) -> None:
    client, _ = admin

    page = client.get("/jobs/nosuchjob")

    assert page.status_code == 404
    assert "text/html" in page.headers["content-type"]
    assert "no job nosuchjob" in page.text


def test_the_fleet_page_shows_unchecked_machines_until_checked_then_online(
        demo_fleet: None, admin: tuple[TestClient, str]) -> None:
    client, csrf = admin
    tile = re.compile(r'data-machine="1010">.*?class="state s-(\w+)"', re.S)

    first = tile.search(client.get("/").text)
    checked = client.post("/check", data={"csrf_token": csrf})
    after = tile.search(client.get("/").text)

    assert first is not None and first.group(1) == "unchecked"
    assert checked.status_code == 303
    assert after is not None and after.group(1) == "online"


def test_the_fleet_page_shows_the_checks_a_worker_made_and_offline_with_why(
        settings: Settings, add_machines: Any, admin: tuple[TestClient, str]) -> None:
    from worker.prober import probe_due

    add_machines({"id": "up", "name": "Up", "model": "Mock"},
                 {"id": "down", "name": "Down", "model": "Mock", "options": {"offline": True}})
    probe_due(settings.model_copy(update={"machine_check_interval_s": 300.0}))
    client, _ = admin
    state = re.compile(r'data-machine="(\w+)">.*?class="state s-(\w+)"', re.S)

    page = client.get("/").text

    assert dict(state.findall(page)) == {"up": "online", "down": "offline"}
    assert "machine is offline (simulated)" in page
    assert "online" in client.get("/m/up").text


def test_a_viewer_is_shown_no_button_to_start_a_rollout(viewer: TestClient) -> None:
    page = viewer.get("/rollout").text

    assert "Start the rollout" not in page and 'value="preview"' not in page
    assert "Rollouts need the programmer role" in page


@pytest.mark.parametrize(("method", "path"), [
    ("get", "/runs/{n}"), ("get", "/runs/{n}/restart"), ("get", "/inbox/{n}"),
    ("post", "/inbox/{n}/approve"), ("post", "/runs/{n}/stop")])
def test_a_number_past_any_row_in_a_pages_address_is_refused_not_a_server_error(
        admin: tuple[TestClient, str], method: str, path: str) -> None:
    client, csrf = admin
    data = {"csrf_token": csrf} if method == "post" else None

    answer = client.request(method, path.format(n=10**20), data=data)

    assert answer.status_code == 400, answer.text  # a bad parameter, as the API answers it
    assert "less than or equal to 9223372036854775807" in answer.text


def test_an_operator_may_not_stop_a_run_job_that_also_runs_on_another_machine(
        filled: dict[str, Any], admin: tuple[TestClient, str], users,
        settings: Settings) -> None:
    client, _ = admin
    program = client.post("/api/programs", content=b"G0 X0\nM30\n", headers={
        **KEY, "content-type": "application/octet-stream"}).json()
    job = client.post("/api/jobs", headers=KEY, json={
        "kind": "dnc_run", "machines": {"ids": ["2001", "2002"]}, "program": program["id"],
        "fileName": "PART.NC", "queue": True}).json()  # behind `filled`'s run on 2001
    on_2001 = next(r["id"] for r in client.get(f"/api/jobs/{job['id']}", headers=KEY)
                   .json()["runs"] if r["machineID"] == "2001")
    users("olga", Role.OPERATOR, machines=("2001",))
    olga = TestClient(dashboard_app(settings), follow_redirects=False)
    csrf = sign_in(olga, "olga", "secret-password")

    answer = olga.post(f"/runs/{on_2001}/stop", data={"csrf_token": csrf})

    assert answer.status_code == 403, answer.text
    assert "may not change machine 2002" in answer.text
    runs = client.get(f"/api/jobs/{job['id']}", headers=KEY).json()["runs"]
    assert not any(r.get("stopRequested") or r["state"] == "stopped" for r in runs)


def _a_backup_of_a1(settings: Settings, status: str, files: dict[str, bytes]) -> None:
    """Backup b1, of machine a1 in `status` with `files` (machine path: bytes)."""
    import hashlib
    import zipfile

    from jobs.backup import store
    from jobs.backup.archive_names import file_path

    folder = store.backup_dir(settings)
    folder.mkdir(parents=True, exist_ok=True)
    members = {path: "B/a1_Lathe/" + file_path(None, (), path.lstrip("/")) for path in files}
    with zipfile.ZipFile(folder / "B.zip", "w") as archive:
        for path, data in files.items():
            archive.writestr(members[path], data)
    with db.session_scope(settings.resolved_database_url) as session:
        store._record(session, "b1", "j1", "B.zip", BackupStatus.COMPLETE, 0, "0" * 64, [{
            "machineID": "a1", "machineName": "Lathe", "status": status, "errorCode": 0,
            "errorMsg": None, "files": [{
                "machine_path": path, "archivePath": members[path], "size": len(data),
                "mtime": None, "sha256": hashlib.sha256(data).hexdigest()}
                for path, data in files.items()]}])


@pytest.mark.parametrize(("model", "path", "folders", "file"), [
    ("Mock", "/sub/a\\b.nc", ["sub"], "a\\b.nc"),  # `\`: a letter on a machine split by `/`
    ("Heidenhain TNC640", "TNC:\\nc_prog\\a\\b.h", ["TNC:", "nc_prog", "a"], "b.h"),
])
def test_a_backups_tree_splits_folders_by_the_machines_own_separator(
        admin: tuple[TestClient, str], add_machines: Any, settings: Settings, model: str,
        path: str, folders: list[str], file: str) -> None:
    add_machines({"id": "a1", "name": "Lathe", "model": model})
    _a_backup_of_a1(settings, "ok", {path: b"G0 X1\n"})
    client, _ = admin

    page = client.get("/backups/b1")

    assert page.status_code == 200, page.text
    assert re.findall(r"<strong>(.*?)/</strong>", page.text) == folders
    shown = re.findall(r'<li class="file"><span class="mono">(.*?)</span>', page.text)
    assert [name.replace("<wbr>", "") for name in shown] == [file]  # where it may wrap


def test_comparing_a_backup_with_the_machine_finds_a_file_with_a_backslash_in_its_name(
        admin: tuple[TestClient, str], add_machines: Any, settings: Settings) -> None:
    from tests.jobs.helpers import on_machine

    add_machines({"id": "a1", "name": "Lathe", "model": "Mock"})
    on_machine(settings, "a1", "sub/a\\b.nc").write_bytes(b"G0 X1\n")  # `\`: a letter here
    _a_backup_of_a1(settings, "ok", {"/sub/a\\b.nc": b"G0 X1\n"})
    client, _ = admin

    page = client.get("/backups/diff", params={"first": "b1", "machine": "a1"})

    assert page.status_code == 200, page.text
    assert "removed 0" in page.text and "No difference." in page.text


def test_comparing_a_backup_with_a_machine_that_is_offline_says_so_and_calls_nothing_removed(
        admin: tuple[TestClient, str], add_machines: Any, settings: Settings) -> None:
    add_machines({"id": "a1", "name": "Lathe", "model": "Mock", "options": {"offline": True}})
    _a_backup_of_a1(settings, "ok", {"/O1000.NC": b"G0 X1\n"})
    client, _ = admin

    page = client.get("/backups/diff", params={"first": "b1", "machine": "a1"})

    assert "20004 machine is offline (simulated)" in page.text
    assert "removed" not in page.text


@pytest.mark.parametrize(("page", "params"), [
    ("/m/a1/download", {"name": "O1000.NC"}),
    ("/backups/diff", {"first": "b1", "machine": "a1"}),
])
def test_a_page_that_cannot_read_its_machine_is_unavailable_not_a_bad_request(
        admin: tuple[TestClient, str], add_machines: Any, settings: Settings, page: str,
        params: dict[str, str]) -> None:
    add_machines({"id": "a1", "name": "Lathe", "model": "Mock", "options": {"offline": True}})
    _a_backup_of_a1(settings, "ok", {"/O1000.NC": b"G0 X1\n"})
    client, _ = admin

    answer = client.get(page, params=params)

    assert answer.status_code == 503
    assert "20004 machine is offline (simulated)" in answer.text


def test_a_page_whose_machine_fails_for_good_is_a_bad_request_not_unavailable(
        admin: tuple[TestClient, str], add_machines: Any, settings: Settings) -> None:
    add_machines({"id": "a1", "name": "Lathe", "model": "Mock"})
    mock_file(settings, "a1", "O1000.NC", "G0 X1\n")
    options = settings.data_dir / "mock" / "a1" / "options.json"
    options.write_text("{offline: true")  # 20006 that will come again: not worth a retry
    client, _ = admin

    answer = client.get("/m/a1/download", params={"name": "O1000.NC"})

    assert answer.status_code == 400
    assert "20006" in answer.text and "not JSON" in answer.text


def test_a_file_with_a_name_beyond_ascii_downloads_under_its_own_name(
        admin: tuple[TestClient, str], add_machines: Any, settings: Settings) -> None:
    add_machines({"id": "a1", "name": "Lathe", "model": "Mock"})
    mock_file(settings, "a1", "Teil ä 部品.nc", "G0 X1\n")
    client, _ = admin

    answer = client.get("/m/a1/download", params={"name": "Teil ä 部品.nc"})

    assert answer.status_code == 200, answer.text
    assert answer.content == b"G0 X1\n"
    said = answer.headers["content-disposition"]
    assert said.isascii()  # raw bytes beyond ASCII read differently in every browser
    assert "filename*=UTF-8''Teil%20%C3%A4%20%E9%83%A8%E5%93%81.nc" in said


def test_comparing_a_backup_that_holds_none_of_a_machine_with_it_says_so(
        admin: tuple[TestClient, str], add_machines: Any, settings: Settings) -> None:
    add_machines({"id": "a1", "name": "Lathe", "model": "Mock"})
    _a_backup_of_a1(settings, "failed", {})
    client, _ = admin

    page = client.get("/backups/diff", params={"first": "b1", "machine": "a1"})

    assert page.status_code == 200, page.text
    assert "Backup b1 holds none of its files (failed)" in page.text
    assert "No difference in the files both hold." in page.text


def test_the_backups_list_names_the_machines_a_partial_backup_failed_on_the_first_few(
        admin: tuple[TestClient, str], settings: Settings) -> None:
    from jobs.backup import store

    statuses = {"m1": "ok", "m2": "failed", "m3": "partial", "m4": "failed", "m5": "failed",
                "m6": "failed"}
    with db.session_scope(settings.resolved_database_url) as session:
        store._record(session, "b1", "j1", "B.zip", BackupStatus.PARTIAL, 0, "0" * 64, [
            {"machineID": m, "machineName": f"Mill {m}", "status": status, "errorCode": 0,
             "errorMsg": None, "files": []} for m, status in statuses.items()])
    client, _ = admin

    page = html.unescape(client.get("/backups").text)

    row = re.search(r'<tr data-backup="b1">(.*?)</tr>', page, re.S)
    assert row is not None
    assert ("failed: m2 Mill m2, m3 Mill m3 (partial), m4 Mill m4 and 2 more"
            in " ".join(row.group(1).split()))


@pytest.mark.parametrize(("asked", "meanwhile"), [("reject", VersionState.APPROVED),
                                                  ("approve", VersionState.REJECTED)])
def test_a_library_version_decided_the_other_way_meanwhile_is_a_conflict_that_says_by_whom(
        filled: dict[str, Any], admin: tuple[TestClient, str], settings: Settings,
        monkeypatch: pytest.MonkeyPatch, asked: str, meanwhile: VersionState) -> None:
    # As the API answers it (409): anna decided between the page's read and its write.
    client, csrf = admin
    version = library.version
    with db.session_scope(settings.resolved_database_url) as session:
        library.decide(session=session, folder="VIPROS", name="0010", number=1, state=(
            VersionState.REJECTED if meanwhile is VersionState.APPROVED
            else VersionState.APPROVED), decided_by="bob")

    def read_then_decided_by_anna(**kwargs: Any) -> Any:
        monkeypatch.setattr(library, "version", version)
        found = version(**kwargs)
        with db.session_scope(settings.resolved_database_url) as other:
            library.decide(session=other, folder="VIPROS", name="0010", number=found.number,
                           state=meanwhile, decided_by="anna")
        return found

    monkeypatch.setattr(library, "version", read_then_decided_by_anna)
    answer = client.post("/library/p/VIPROS/0010/decide",
                         data={"csrf_token": csrf, "number": "1", "decision": asked})

    assert answer.status_code == 303
    told = html.unescape(client.get(answer.headers["location"]).text)
    done = "approved" if asked == "approve" else "rejected"
    assert (f"Not decided: VIPROS/0010 v1 was {meanwhile.value} meanwhile by anna; it was not "
            f"{done}. Their decision stands.") in told
    with db.session_scope(settings.resolved_database_url) as session:
        [written] = audit.list_events(session=session, action=f"{asked} library version")
        assert (written.who, written.target, written.status) == ("admin", "VIPROS/0010 v1", 409)
        kept = library.version(session=session, folder="VIPROS", name="0010", number=1)
        assert (kept.state, kept.decided_by) == (meanwhile, "anna")


def test_a_library_decision_neither_approve_nor_reject_decides_nothing(
        filled: dict[str, Any], admin: tuple[TestClient, str], settings: Settings) -> None:
    # A form made by hand (or a page of another version) must not reject for a word it
    # does not understand: before, any decision but approve rejected the version.
    client, csrf = admin
    with db.session_scope(settings.resolved_database_url) as session:
        v1 = library.version(session=session, folder="VIPROS", name="0010", number=1)
        before = (v1.state, v1.decided_by, v1.decided_at)

    answer = client.post("/library/p/VIPROS/0010/decide",
                         data={"csrf_token": csrf, "number": "1", "decision": "delete"})

    assert answer.status_code == 303
    assert "Not decided: 'delete' is neither approve nor reject." in html.unescape(
        client.get(answer.headers["location"]).text)
    with db.session_scope(settings.resolved_database_url) as session:
        v1 = library.version(session=session, folder="VIPROS", name="0010", number=1)
        assert (v1.state, v1.decided_by, v1.decided_at) == before
        [written] = audit.list_events(session=session, action="decide library version")
        assert (written.who, written.target, written.status) == ("admin", "VIPROS/0010 v1", 400)


@pytest.mark.parametrize("asked", ["approve", "reject"])
def test_an_inbox_item_approved_meanwhile_is_a_conflict_in_the_audit_trail_as_in_the_api(
        filled: dict[str, Any], admin: tuple[TestClient, str], settings: Settings,
        asked: str) -> None:
    client, csrf = admin
    item = filled["item"]
    with db.session_scope(settings.resolved_database_url) as session:
        inbox.approve(session=session, settings=settings, item_id=item, decided_by="anna")
    by_api = client.post(f"/api/inbox/{item}/{asked}", headers=KEY, json={})

    answer = client.post(f"/inbox/{item}/{asked}", data={"csrf_token": csrf})

    assert by_api.status_code == 409
    assert answer.status_code == 303
    assert "is approved already, as VIPROS/0077 v" in html.unescape(
        client.get(answer.headers["location"]).text)
    with db.session_scope(settings.resolved_database_url) as session:
        [written] = audit.list_events(session=session, action=f"{asked} inbox item")
        assert (written.who, written.target, written.status) == ("admin", str(item), 409)
        assert inbox.get(session=session, item_id=item).decided_by == "anna"


# A refusal asked of the dashboard and of the API alike: the form, its audit action, and
# the API's request for the same thing.
SAME_REFUSALS = {
    "missing library version": (
        "/library/p/VIPROS/0010/decide", {"number": "99", "decision": "approve"},
        "approve library version", "POST", "/api/library/approve/VIPROS/0010?version=99",
        None),
    "missing inbox item": (
        "/inbox/999999/approve", {}, "approve inbox item", "POST",
        "/api/inbox/999999/approve", {}),
    "upload to a missing machine": (
        "/m/9999/upload", {"dir": ""}, "send file", "POST",
        "/machines/9999/api/files/local", None),
    "retry of a missing job": (
        "/jobs/nojob/retry", {}, "retry job", "POST", "/api/jobs/nojob/retry", None),
    "missing schedule run": (
        "/schedules/nope/run", {}, "run schedule", "POST", "/api/schedules/nope/run", None),
    "user name taken": (
        "/admin/users", {"name": "anna", "role": "viewer", "password": "secret-password",
                         "password_again": "secret-password"},
        "add user", "POST", "/api/users",
        {"name": "anna", "role": "viewer", "password": "secret-password"}),
    "password too short": (
        "/admin/users", {"name": "bert", "role": "viewer", "password": "short",
                         "password_again": "short"},
        "add user", "POST", "/api/users", {"name": "bert", "role": "viewer", "password": "short"}),
    "schedule of machines no one has": (
        "/schedules", {"name": "nightly", "cron": "0 2 * * *", "ids": "9999"},
        "save schedule", "POST", "/api/schedules",
        {"name": "nightly", "cron": "0 2 * * *", "machines": {"ids": ["9999"]}}),
    "restore onto a machine no one has": (
        "/backups/b1/restore", {"machine": "9999"}, "restore backup", "POST",
        "/api/backups/b1/restore", {"machine": "9999"}),
    "put back what a job that replaced nothing replaced": (
        "/jobs/{job}/restore-replaced", {}, "restore replaced files", "POST",
        "/api/jobs/{job}/restore-replaced", None),
    # refused before any of the route's own records: these left no entry at all
    "stop of a missing run": (
        "/runs/999999/stop", {}, "stop run", "POST", "/api/jobs/nojob/stop", None),
    "restart of a missing run": (
        "/runs/999999/restart", {"action": "start", "kind": "block", "point": "N10"},
        "restart run", "GET", "/api/runs/999999", None),
    "cancel of a missing job": (
        "/jobs/nojob/cancel", {}, "cancel job", "POST", "/api/jobs/nojob/cancel", None),
    "put back what a missing job replaced": (
        "/jobs/nojob/restore-replaced", {}, "restore replaced files", "POST",
        "/api/jobs/nojob/restore-replaced", None),
    "change of a missing user": (
        "/admin/users/nobody/set", {"role": "viewer"}, "change user", "PATCH",
        "/api/users/nobody", {"role": "viewer"}),
    "password of a missing user": (
        "/admin/users/nobody/password", {"password": "secret-password",
                                         "password_again": "secret-password"},
        "set password", "PATCH", "/api/users/nobody", {"password": "secret-password"}),
    "disable of a missing user": (
        "/admin/users/nobody/disable", {}, "disable user", "PATCH", "/api/users/nobody",
        {"disabled": True}),
    "enable of a missing user": (
        "/admin/users/nobody/enable", {}, "enable user", "PATCH", "/api/users/nobody",
        {"disabled": False}),
    "removal of a missing user": (
        "/admin/users/nobody/delete", {}, "delete user", "DELETE", "/api/users/nobody", None),
    "revoke of a missing key": (
        "/admin/keys/nokey/revoke", {}, "revoke key", "DELETE", "/api/keys/nokey", None),
    "verify of a missing backup": (
        "/backups/nob/verify", {}, "verify backup", "POST", "/api/backups/nob/verify", None),
    "restore of a missing backup": (
        "/backups/nob/restore", {"machine": "1010"}, "restore backup", "POST",
        "/api/backups/nob/restore", {"machine": "1010"}),
    "enable of a missing schedule": (
        "/schedules/nope/enable", {}, "enable schedule", "POST",
        "/api/schedules/nope/enable", None),
    "disable of a missing schedule": (
        "/schedules/nope/disable", {}, "disable schedule", "POST",
        "/api/schedules/nope/disable", None),
    "removal of a missing schedule": (
        "/schedules/nope/delete", {}, "delete schedule", "DELETE", "/api/schedules/nope", None),
    "check of a missing machine": (
        "/m/9999/check", {}, "check machine", "POST", "/api/machines/check",
        {"ids": ["9999"]}),
}


@pytest.mark.parametrize("case", SAME_REFUSALS)
def test_a_refusal_on_the_dashboard_is_in_the_audit_trail_with_the_status_the_api_answers(
        filled: dict[str, Any], admin: tuple[TestClient, str], settings: Settings,
        users: Any, case: str) -> None:
    # The trail said 400 for each, where the API answers 404, 409, 413 or 422.
    from jobs.backup import store

    page, form, action, method, api_path, body = SAME_REFUSALS[case]
    users("anna", Role.VIEWER)
    with db.session_scope(settings.resolved_database_url) as session:
        store._record(session, "b1", "j1", "B.zip", BackupStatus.COMPLETE, 0, "0" * 64, [])
    client, csrf = admin
    files = {"file": ("O0077", PROGRAM)} if page.endswith("/upload") else None
    by_api = client.request(method, api_path.format(**filled), headers=KEY, json=body,
                            files=files)

    answer = client.post(page.format(**filled), data={"csrf_token": csrf, **form},
                         files=files)

    assert by_api.status_code in (404, 409, 413, 422), by_api.text
    if answer.status_code >= 400:  # a page that says the refusal: with the API's status
        assert answer.status_code == by_api.status_code, answer.text[-2000:]
    with db.session_scope(settings.resolved_database_url) as session:
        [written] = audit.list_events(session=session, action=action)
        assert (written.who, written.status) == ("admin", by_api.status_code)


def test_a_read_or_a_preview_refused_on_the_dashboard_is_not_in_the_audit_trail(
        admin: tuple[TestClient, str], settings: Settings) -> None:
    # Only a change is recorded, as the API records only its state-changing requests.
    client, csrf = admin

    read = client.get("/runs/999999")
    preview = client.post("/runs/999999/restart", data={"csrf_token": csrf, "action": "preview",
                                                        "kind": "block", "point": "N10"})
    started = client.post("/runs/999999/restart", data={"csrf_token": csrf, "action": "start",
                                                        "kind": "block", "point": "N10"})

    assert (read.status_code, preview.status_code, started.status_code) == (404, 404, 404)
    with db.session_scope(settings.resolved_database_url) as session:
        written = [(e.method, e.action, e.status) for e in audit.list_events(session=session)
                   if e.path.startswith("/runs/")]
    assert written == [("POST", "restart run", 404)]
