"""The schedules page's add, change, pause and remove, and a drip-feed run's restart from a
block (previewed, started, refused), server side."""

from __future__ import annotations

import html
import re
from datetime import UTC, datetime
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select, update

from jobs import db, schedules
from jobs.auth import audit
from jobs.backup import follow_up
from jobs.backup_models import Schedule, ScheduleRun
from jobs.models import Job, JobKind, Run, RunState
from jobs.settings import Settings
from jobs.web.principal import Role
from tests.conftest import API_KEY
from tests.jobs.web.conftest import dashboard_app, sign_in

KEY = {"X-Api-Key": API_KEY}
PROGRAM = (b"%\nO9000 (BRACKET)\nG17 G21 G40 G49 G80 G90 G94\nT12 M6\n"
           b"G54 G0 X0. Y0. S8000 M3\nG43 H12 Z5. M8\nG1 Z-1. F1500.\n"
           b"N8 X10. Y0.5\nN9 X20. Y1.5\nN10 X30. Y2.5\nM30\n%\n")


def _schedule(settings: Settings, name: str) -> Schedule | None:
    with db.session_scope(settings.resolved_database_url) as session:
        found = session.get(Schedule, name)
        if found is not None:
            session.expunge(found)
        return found


def _save(client: TestClient, csrf: str, **fields: Any) -> Any:
    form = {"csrf_token": csrf, "name": "nightly", "cron": "0 2 * * *",
            "timezone": "Europe/Berlin", "ids": "1010, 1011", "retention": "last=3,daily=14",
            "enabled": "on", **fields}
    return client.post("/schedules", data={k: v for k, v in form.items() if v is not None})


# -- schedules -----------------------------------------------------------------------

def test_a_schedule_naming_an_unknown_machine_is_not_saved_and_the_page_says_why(
        demo_fleet: None, admin: tuple[TestClient, str]) -> None:
    client, csrf = admin

    answer = _save(client, csrf, ids="1010, 9999")

    assert answer.status_code == 422  # as the API answers it
    assert "Schedule nightly not saved: no machine 9999" in answer.text
    assert 'data-schedule="nightly"' not in client.get("/schedules").text


def _edit_form(client: TestClient, name: str) -> dict[str, str]:
    """The hidden fields of the edit form of `name` as the page shows it now."""
    page = client.get("/schedules", params={"edit": name}).text
    return dict(re.findall(r'<input type="hidden" name="(editing|shown_enabled)" '
                           r'value="([^"]*)">', page))


@pytest.mark.parametrize("meanwhile", ["disable", "delete"])
def test_an_edit_form_opened_before_another_admin_disabled_or_removed_does_not_undo_it(
        demo_fleet: None, admin: tuple[TestClient, str], settings: Settings,
        meanwhile: str) -> None:
    client, csrf = admin
    _save(client, csrf)
    opened = _edit_form(client, "nightly")
    assert opened == {"editing": "on", "shown_enabled": "on"}

    client.post(f"/schedules/nightly/{meanwhile}", data={"csrf_token": csrf})
    saved = _save(client, csrf, cron="0 3 * * *", **opened)

    assert saved.status_code == 303
    with db.session_scope(settings.resolved_database_url) as session:
        schedule = session.get(Schedule, "nightly")
        if meanwhile == "delete":
            assert schedule is None  # not added back
            assert "removed meanwhile" in client.get(saved.headers["location"]).text
        else:
            assert schedule is not None and schedule.cron == "0 3 * * *"
            assert not schedule.enabled  # the other admin's Disable stands


def test_an_admin_adds_a_schedule_from_the_page(
        demo_fleet: None, admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin

    answer = _save(client, csrf)

    assert answer.status_code == 303
    stored = _schedule(settings, "nightly")
    assert stored is not None
    assert (stored.cron, stored.timezone, stored.retention, stored.enabled) == (
        "0 2 * * *", "Europe/Berlin", "last=3,daily=14", True)
    assert stored.machines == {"ids": ["1010", "1011"], "tags": [], "all": False}
    page = client.get(answer.headers["location"]).text
    assert "Added schedule nightly" in page
    # Its next run in the zone its cron is read in, named: not the server's hour, bare.
    assert re.search(r"<span>\d{4}-\d\d-\d\d</span> <span>02:00 Europe/Berlin</span></time></td>",
                     page), page


def test_an_admin_changes_a_schedule_and_its_alert_urls_are_kept(
        demo_fleet: None, admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin
    _save(client, csrf, notify="https://hooks.example/backup")
    form = client.get("/schedules?edit=nightly").text
    assert "Change the schedule nightly" in form and 'value="0 2 * * *"' in form

    answer = _save(client, csrf, cron="30 3 * * 1-5", ids="", tags="mills", enabled=None)

    assert answer.status_code == 303
    stored = _schedule(settings, "nightly")
    assert stored is not None
    assert (stored.cron, stored.enabled) == ("30 3 * * 1-5", False)
    assert stored.machines == {"ids": [], "tags": ["mills"], "all": False}
    assert "hooks.example" not in str(stored.notify)  # sealed
    assert follow_up.alert_urls(settings, stored) == ["https://hooks.example/backup"]


def test_an_admin_removes_a_schedules_alert_urls_from_the_page(
        demo_fleet: None, admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin
    _save(client, csrf, notify="https://hooks.example/backup")

    answer = _save(client, csrf, clear_alerts="on")

    assert answer.status_code == 303
    stored = _schedule(settings, "nightly")
    assert stored is not None and stored.notify == []


def test_a_schedule_of_every_machine_is_saved_as_all(
        demo_fleet: None, admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin

    _save(client, csrf, ids="", all="on")

    stored = _schedule(settings, "nightly")
    assert stored is not None and stored.machines == {"ids": [], "tags": [], "all": True}


def test_a_bad_cron_is_refused_with_its_reason_and_nothing_is_saved(
        demo_fleet: None, admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin

    answer = _save(client, csrf, cron="0 25 * * *")

    assert answer.status_code == 400
    assert "Schedule nightly not saved: cron:" in answer.text
    assert "not a cron expression: &#39;0 25 * * *&#39;" in answer.text
    assert 'value="0 25 * * *"' in answer.text  # the form keeps what was typed
    assert _schedule(settings, "nightly") is None


def test_a_schedule_selecting_no_machine_is_refused_as_the_api_refuses_it(
        demo_fleet: None, admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin

    answer = _save(client, csrf, ids="")

    assert answer.status_code == 400
    assert "no machine selected: give ids, tags or all" in answer.text
    assert _schedule(settings, "nightly") is None


def test_an_admin_disables_enables_and_removes_a_schedule(
        demo_fleet: None, admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin
    _save(client, csrf)

    client.post("/schedules/nightly/disable", data={"csrf_token": csrf})
    disabled = _schedule(settings, "nightly")
    client.post("/schedules/nightly/enable", data={"csrf_token": csrf})
    enabled = _schedule(settings, "nightly")
    removed = client.post("/schedules/nightly/delete", data={"csrf_token": csrf})

    assert disabled is not None and not disabled.enabled
    assert enabled is not None and enabled.enabled
    assert removed.status_code == 303 and _schedule(settings, "nightly") is None


def test_pausing_a_schedule_that_is_gone_is_not_found(admin: tuple[TestClient, str]) -> None:
    client, csrf = admin

    answer = client.post("/schedules/nightly/disable", data={"csrf_token": csrf})

    assert answer.status_code == 404 and "no schedule nightly" in answer.text


@pytest.mark.parametrize("path", ["/schedules", "/schedules/nightly/disable",
                                  "/schedules/nightly/delete"])
def test_an_operators_schedule_change_is_refused_with_403(
        demo_fleet: None, admin: tuple[TestClient, str], users, settings: Settings,
        path: str) -> None:
    _save(*admin)
    users("otto", Role.OPERATOR)
    client = TestClient(dashboard_app(settings), follow_redirects=False)
    csrf = sign_in(client, "otto", "secret-password")

    answer = client.post(path, data={"csrf_token": csrf, "name": "nightly",
                                     "cron": "* * * * *", "all": "on"})

    assert answer.status_code == 403 and "you (otto) are an operator" in answer.text
    stored = _schedule(settings, "nightly")
    assert stored is not None and stored.cron == "0 2 * * *" and stored.enabled


def test_an_operator_sees_no_schedule_form(
        demo_fleet: None, users, settings: Settings) -> None:
    users("otto", Role.OPERATOR)
    client = TestClient(dashboard_app(settings), follow_redirects=False)
    sign_in(client, "otto", "secret-password")

    assert 'action="/schedules"' not in client.get("/schedules").text


def test_the_page_says_which_pass_of_the_repeated_hour_a_schedules_runs_are(
        demo_fleet: None, admin: tuple[TestClient, str], settings: Settings,
        monkeypatch: pytest.MonkeyPatch) -> None:
    # Berlin, 25 October 2026, 02:10 CET: the hourly backup of 02:00 summer time ran, the
    # clocks went back to 02:00, and the next one is 02:00 winter time.
    client, csrf = admin
    _save(client, csrf, cron="0 * * * *")
    schedules.run_now(settings=settings, name="nightly")
    with db.session_scope(settings.resolved_database_url) as session:
        session.execute(update(ScheduleRun).values(
            fire_at=datetime(2026, 10, 25, 0, 0, tzinfo=UTC)))
    monkeypatch.setattr(schedules, "utcnow", lambda: datetime(2026, 10, 25, 0, 10, tzinfo=UTC))

    page = client.get("/schedules").text

    row = re.search(r'<tr data-schedule="nightly">.*?</tr>', page, re.S)
    assert row is not None
    cells = [html.unescape(re.sub(r"<[^>]+>", "", c)).strip()
             for c in re.findall(r"<td[^>]*>(.*?)</td>", row[0], re.S)]
    assert cells[3:5] == ["2026-10-25 02:00 CET Europe/Berlin",
                          "2026-10-25 02:00 CEST Europe/Berlin"]


# -- restart from a block --------------------------------------------------------------

@pytest.fixture
def failed_run(demo_fleet: None, admin: tuple[TestClient, str], settings: Settings) -> int:
    """A run of PROGRAM on 1010 that failed at line 9 (its link lost)."""
    client, _ = admin
    program = client.post("/api/programs", content=PROGRAM, headers={
        **KEY, "content-type": "application/octet-stream"}).json()
    job = client.post("/api/jobs", headers=KEY, json={
        "kind": "dnc_run", "machines": {"ids": ["1010"]}, "program": program["id"],
        "fileName": "BRACKET.NC"}).json()
    with db.session_scope(settings.resolved_database_url) as session:
        run = session.scalars(select(Run).where(Run.job_id == job["id"])).one()
        run.state, run.last_line, run.message = RunState.FAILED, 9, "link lost"
        return run.id


def _restart(client: TestClient, csrf: str, run_id: int, action: str,
             point: str = "N9", form_key: str | None = None, **more: str) -> Any:
    return client.post(f"/runs/{run_id}/restart", data={
        "csrf_token": csrf, "kind": "block", "point": point, "action": action,
        **({"form_key": form_key} if form_key else {}), **more})


def _notice(page: str) -> str:
    found = re.search(r"data-restart-error>([^<]*)<", page)
    assert found, "the page says no reason"
    return html.unescape(found.group(1))


def test_a_failed_runs_row_offers_its_restart(failed_run: int,
                                              admin: tuple[TestClient, str]) -> None:
    client, _ = admin

    page = client.get("/runs").text

    assert f'href="/runs/{failed_run}/restart"' in page


def test_the_restart_page_asks_for_the_point(failed_run: int,
                                             admin: tuple[TestClient, str]) -> None:
    client, _ = admin

    page = client.get(f"/runs/{failed_run}/restart")

    assert page.status_code == 200
    assert 'name="point"' in page.text and "Preview the header" in page.text
    assert "Start the restart" not in page.text  # only once previewed


def test_the_restart_preview_shows_the_header_and_start_line_and_starts_nothing(
        failed_run: int, admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin

    answer = _restart(client, csrf, failed_run, "preview")

    assert answer.status_code == 200, answer.text
    assert 'data-start-line>9<' in answer.text
    assert "T12 M6" in answer.text and "G43 H12" in answer.text
    assert "Start the restart" in answer.text
    with db.session_scope(settings.resolved_database_url) as session:
        assert len(session.scalars(select(Run)).all()) == 1


def test_start_submits_a_dnc_run_job_from_the_restart_point(
        failed_run: int, admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin

    answer = _restart(client, csrf, failed_run, "start")

    assert answer.status_code == 303, answer.text
    new_id = int(answer.headers["location"].rsplit("/", 1)[1])
    with db.session_scope(settings.resolved_database_url) as session:
        run = session.get(Run, new_id)
        assert run is not None and run.id != failed_run
        assert (run.machine_id, run.program_name, run.start_line, run.restart_from) == (
            "1010", "BRACKET.NC", 9, "block N9")
        assert "T12 M6" in run.header
        job = session.get(Job, run.job_id)
        assert job is not None and job.kind is JobKind.DNC_RUN
        assert job.created_by == "admin"


def test_a_restart_form_sent_twice_starts_one_run(
        failed_run: int, admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin
    page = client.get(f"/runs/{failed_run}/restart").text
    key = re.search(r'name="form_key" value="([^"]+)"', page)
    assert key, "the restart form carries no one-time key"

    previewed = _restart(client, csrf, failed_run, "preview", form_key=key.group(1))
    first = _restart(client, csrf, failed_run, "start", form_key=key.group(1))
    second = _restart(client, csrf, failed_run, "start", form_key=key.group(1))

    assert previewed.status_code == 200  # a preview starts nothing and keeps the key
    assert first.status_code == 303, first.text
    assert second.status_code == 409 and "sent already" in second.text
    with db.session_scope(settings.resolved_database_url) as session:
        assert len(session.scalars(select(Run)).all()) == 2  # the failed one and one restart


def test_a_block_the_program_lacks_is_refused_with_its_reason(
        failed_run: int, admin: tuple[TestClient, str], settings: Settings) -> None:
    client, csrf = admin

    answer = _restart(client, csrf, failed_run, "start", point="N99")

    assert answer.status_code == 422
    notice = _notice(answer.text)
    assert notice.startswith("Not restarted: cannot restart:") and "N99" in notice, notice
    with db.session_scope(settings.resolved_database_url) as session:
        assert len(session.scalars(select(Run)).all()) == 1
        # the trail says what the page and the API's restart answer, where it said 400
        [written] = audit.list_events(session=session, action="restart run")
        assert written.status == 422


def test_text_that_is_not_a_block_is_refused_with_its_reason(
        failed_run: int, admin: tuple[TestClient, str]) -> None:
    client, csrf = admin

    answer = _restart(client, csrf, failed_run, "preview", point="X12")

    assert answer.status_code == 422
    assert _notice(answer.text).startswith("Not restarted: cannot restart:")


def test_an_operator_not_allowed_the_machine_may_not_restart_its_run(
        failed_run: int, users, settings: Settings) -> None:
    users("otto", Role.OPERATOR, machines=("1011",))
    client = TestClient(dashboard_app(settings), follow_redirects=False)
    csrf = sign_in(client, "otto", "secret-password")

    answer = _restart(client, csrf, failed_run, "start")

    assert answer.status_code == 403
    assert "may not change machine 1010; your machines: 1011" in answer.text


def test_a_viewers_restart_is_refused_with_403(failed_run: int, users,
                                               settings: Settings) -> None:
    users("vera", Role.VIEWER)
    client = TestClient(dashboard_app(settings), follow_redirects=False)
    csrf = sign_in(client, "vera", "secret-password")

    answer = _restart(client, csrf, failed_run, "start")

    assert answer.status_code == 403 and "you (vera) are a viewer" in answer.text
    assert f'/runs/{failed_run}/restart"' not in client.get("/runs").text


def _set_state(settings: Settings, run_id: int, state: RunState) -> None:
    with db.session_scope(settings.resolved_database_url) as session:
        run = session.get(Run, run_id)
        assert run is not None
        run.state = state


def test_a_queued_run_is_not_restarted(failed_run: int, admin: tuple[TestClient, str],
                                       settings: Settings) -> None:
    client, csrf = admin
    _set_state(settings, failed_run, RunState.QUEUED)

    answer = _restart(client, csrf, failed_run, "start")

    assert answer.status_code == 409 and "only a run that has ended" in answer.text


def test_a_run_not_ended_restarted_is_in_the_audit_trail_as_a_conflict_and_its_preview_not(
        failed_run: int, admin: tuple[TestClient, str], settings: Settings) -> None:
    # Refused with 409 on the page, as the API refuses a run asked of a machine still
    # running one, and left no entry at all.
    client, csrf = admin
    _set_state(settings, failed_run, RunState.RUNNING)

    previewed = _restart(client, csrf, failed_run, "preview")
    started = _restart(client, csrf, failed_run, "start")

    assert (previewed.status_code, started.status_code) == (409, 409)
    with db.session_scope(settings.resolved_database_url) as session:
        written = [(e.who, e.action, e.status, e.target)
                   for e in audit.list_events(session=session, action="restart run")]
        assert written == [("admin", "restart run", 409, str(failed_run))]
        assert len(session.scalars(select(Run)).all()) == 1


def test_a_restart_on_a_machine_with_a_run_not_ended_is_refused_naming_it_unless_queued(
        failed_run: int, admin: tuple[TestClient, str], settings: Settings) -> None:
    # It answered the generic page with 503, as if the machine could not be reached, told
    # to queue it with an option the form did not have, and left no trace in the audit.
    client, csrf = admin
    program = client.post("/api/programs", content=PROGRAM, headers={
        **KEY, "content-type": "application/octet-stream"}).json()
    other = client.post("/api/jobs", headers=KEY, json={
        "kind": "dnc_run", "machines": {"ids": ["1010"]}, "program": program["id"],
        "fileName": "OTHER.NC"}).json()

    refused = _restart(client, csrf, failed_run, "start")
    queued = _restart(client, csrf, failed_run, "start", queue="on")

    assert refused.status_code == 409
    notice = _notice(refused.text)
    assert notice.startswith("Not restarted: machine 1010 has a drip-feed run queued "
                             f"(job {other['id']}, OTHER.NC)"), notice
    assert 'name="queue"' in refused.text and "Start the restart" in refused.text
    assert queued.status_code == 303, queued.text
    with db.session_scope(settings.resolved_database_url) as session:
        events = [(e.action, e.status) for e in audit.list_events(session=session, limit=10)]
        assert sorted(session.scalars(select(Run.state))) == [
            RunState.FAILED, RunState.QUEUED, RunState.QUEUED]
    assert ("restart run", 409) in events and ("restart run", 200) in events
