"""Backup schedules: due fires, one run per fire time, retention after a run, alerts."""

from __future__ import annotations

import threading
import zoneinfo
from datetime import UTC, datetime, timedelta
from typing import Any
from zoneinfo import ZoneInfo

import pytest
from sqlalchemy import delete, func, select, text, update
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import Session

from jobs import db, schedules
from jobs.backup import follow_up
from jobs.backup_models import (
    Backup,
    BackupMachine,
    BackupStatus,
    MachineBackupStatus,
    Schedule,
    ScheduleRun,
)
from jobs.fleet import sealed
from jobs.models import Machine, utcnow
from jobs.run import queue
from tests.jobs.helpers import wait_done, wait_until


@pytest.fixture
def alerts(webhook_server):
    """A loopback webhook that records every alert."""
    return webhook_server()


@pytest.fixture
def queue_settings(queue_settings, alerts):  # noqa: F811 - extends the shared fixture
    return queue_settings.model_copy(update={"notify_urls": [alerts.url()]})


def add_schedule(settings: Any, created: datetime, **fields: Any) -> None:
    with db.session_scope(settings.resolved_database_url) as session:
        schedules.upsert(
            session=session, data_dir=settings.data_dir, schedule_in=schedules.ScheduleIn(
                name="nightly", cron="0 2 * * *", timezone="Europe/Berlin", **fields))
        session.execute(update(Schedule).values(created_at=created))


def runs(settings: Any) -> list[tuple[datetime, str | None]]:
    with db.session_scope(settings.resolved_database_url) as session:
        return [(r.fire_at, r.job_id) for r in session.scalars(
            select(ScheduleRun).order_by(ScheduleRun.fire_at))]


def backups_count(settings: Any) -> int:
    with db.session_scope(settings.resolved_database_url) as session:
        return session.scalar(select(func.count()).select_from(Backup)) or 0


def fleet(add_machines: Any, settings: Any, **options: Any) -> None:
    add_machines({"id": "a1", "name": "Lathe", "model": "Mock", "options": options})
    path = settings.data_dir / "mock" / "a1" / "files" / "P1.nc"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("G0 X1\n")


BERLIN_2AM_UTC = datetime(2026, 11, 20, 1, 0, tzinfo=UTC)  # 02:00 in Berlin (CET)


def test_a_schedule_is_not_due_before_its_first_fire_time(settings):
    add_schedule(settings, created=BERLIN_2AM_UTC + timedelta(hours=10))
    later_same_day = BERLIN_2AM_UTC + timedelta(hours=20)
    assert schedules.tick(settings=settings, now=later_same_day) == []
    assert runs(settings) == []


def test_a_schedule_fires_at_its_time_in_its_time_zone(queue_client, settings, add_machines,
                                                       queue_settings):
    fleet(add_machines, queue_settings)
    add_schedule(queue_settings, created=BERLIN_2AM_UTC - timedelta(days=1))
    [job_id] = schedules.tick(settings=queue_settings, now=BERLIN_2AM_UTC + timedelta(minutes=1))
    assert runs(queue_settings) == [(BERLIN_2AM_UTC, job_id)]
    wait_done(queue_client, job_id)
    wait_until(lambda: backups_count(queue_settings) == 1)


def test_a_schedule_whose_tags_match_no_machine_alerts_and_the_others_still_run(
        queue_client, add_machines, queue_settings, alerts):
    fleet(add_machines, queue_settings)
    add_machines({"id": "ghost", "name": "Ghost", "model": "Mock", "tags": ["gone"]})
    with db.session_scope(queue_settings.resolved_database_url) as session:
        schedules.upsert(
            session=session, data_dir=queue_settings.data_dir, schedule_in=schedules.ScheduleIn(
                name="a-ghost", cron="0 2 * * *", machines={"tags": ["gone"]}))
        session.execute(update(Schedule).values(created_at=BERLIN_2AM_UTC - timedelta(days=1)))
        session.execute(delete(Machine).where(Machine.id == "ghost"))  # removed since
    add_schedule(queue_settings, created=BERLIN_2AM_UTC - timedelta(days=1))

    started = schedules.tick(settings=queue_settings, now=BERLIN_2AM_UTC + timedelta(hours=1))

    assert len(started) == 1  # "nightly" ran although "a-ghost" came first and failed
    wait_until(lambda: bool(alerts.requests))
    assert "a-ghost backed up nothing" in alerts.requests[0].json()["title"]
    wait_done(queue_client, started[0])


@pytest.mark.parametrize(("machines", "said"), [
    ({"ids": ["9999"]}, "no machine 9999"),
    ({"ids": ["1O10"]}, "no machine 1O10 (did you mean 1010?)"),
    ({"tags": ["nosuch"]}, "no machine tagged nosuch")])
def test_a_schedule_naming_machines_no_one_has_is_refused_and_not_saved(
        client, demo_fleet, machines, said):
    answer = client.post("/api/schedules", json={"name": "typo", "cron": "0 2 * * *",
                                                 "machines": machines})

    assert answer.status_code == 422 and said in answer.json()["statusMsg"]
    assert client.get("/api/schedules").json() == []


def test_missed_nights_run_once_and_a_second_tick_does_not_double_it(
        queue_client, add_machines, queue_settings):
    fleet(add_machines, queue_settings)
    add_schedule(queue_settings, created=BERLIN_2AM_UTC - timedelta(days=10))
    back_after_five_nights = BERLIN_2AM_UTC + timedelta(days=4, hours=9)
    first = schedules.tick(settings=queue_settings, now=back_after_five_nights)
    again = schedules.tick(settings=queue_settings, now=back_after_five_nights)  # a 2nd beat
    assert len(first) == 1 and again == []
    assert [fire for fire, _ in runs(queue_settings)] == [BERLIN_2AM_UTC + timedelta(days=4)]
    wait_done(queue_client, first[0])


def test_a_run_now_just_after_a_fire_time_does_not_take_that_fire(
        queue_client, add_machines, queue_settings):
    fleet(add_machines, queue_settings)
    add_schedule(queue_settings, created=utcnow() - timedelta(days=1))
    by_hand = schedules.run_now(settings=queue_settings, name="nightly")
    [(pressed_at, _)] = runs(queue_settings)
    fire = pressed_at.replace(second=0, microsecond=0)  # the fire just before the press
    local = fire.astimezone(ZoneInfo("Europe/Berlin"))
    with db.session_scope(queue_settings.resolved_database_url) as session:
        session.execute(update(Schedule).values(cron=f"{local.minute} {local.hour} * * *"))

    started = schedules.tick(settings=queue_settings, now=pressed_at + timedelta(seconds=20))

    assert len(started) == 1
    assert runs(queue_settings) == [(fire, started[0]), (pressed_at, by_hand)]
    wait_done(queue_client, by_hand)
    wait_done(queue_client, started[0])


@pytest.mark.parametrize("resume", ["enable", "save"])
def test_a_schedule_enabled_after_a_pause_runs_at_its_next_time_not_the_one_it_missed(
        database_url, tmp_path, resume):
    name = f"nightly-{resume}"
    with db.session_scope(database_url) as session:  # paused for a week
        schedules.upsert(session=session, data_dir=tmp_path, schedule_in=schedules.ScheduleIn(
            name=name, cron="0 2 * * *", timezone="Europe/Berlin", enabled=False))
        session.execute(update(Schedule).where(Schedule.name == name)
                        .values(created_at=utcnow() - timedelta(days=7)))
    with db.session_scope(database_url) as session:  # `dncq schedule enable`, or a save
        if resume == "enable":
            schedules.set_enabled(session=session, name=name, enabled=True)
        else:
            schedules.upsert(session=session, data_dir=tmp_path, schedule_in=schedules.ScheduleIn(
                name=name, cron="0 2 * * *", timezone="Europe/Berlin", enabled=True))

    now = utcnow()
    with db.session_scope(database_url) as session:
        schedule = schedules.get(session=session, name=name)
        tonight = schedules.view(session, schedule, now=now)["nextRun"]
        assert schedules.due_fire(schedule, None, now) is None  # last night's is not run now
        assert schedules.due_fire(schedule, None, tonight + timedelta(minutes=1)) == tonight


@pytest.mark.parametrize(("name", "change"), [
    ("earlier", {"cron": "30 1 * * *"}), ("elsewhere", {"timezone": "Asia/Tokyo"})])
def test_a_schedule_given_other_times_runs_at_the_next_of_them_not_at_once(
        database_url, tmp_path, name: str, change: dict[str, str]) -> None:
    # A nightly 02:00 moved to 01:30 (or to another zone) in the afternoon: today's 01:30
    # had not run, and the scheduler's next tick ran the fleet's backup mid-shift.
    old = {"cron": "0 2 * * *", "timezone": "Europe/Berlin"}
    with db.session_scope(database_url) as session:
        schedules.upsert(session=session, data_dir=tmp_path,
                         schedule_in=schedules.ScheduleIn(name=name, **old))
        session.execute(update(Schedule).where(Schedule.name == name)
                        .values(created_at=utcnow() - timedelta(days=7)))
    with db.session_scope(database_url) as session:
        schedules.upsert(session=session, data_dir=tmp_path, schedule_in=schedules.ScheduleIn(
            name=name, **{**old, **change}))

    now = utcnow()
    with db.session_scope(database_url) as session:
        schedule = schedules.get(session=session, name=name)
        upcoming = schedules.view(session, schedule, now=now)["nextRun"]
        assert schedules.due_fire(schedule, None, now) is None
        assert schedules.due_fire(schedule, None, upcoming + timedelta(minutes=1)) == upcoming


def test_retention_prunes_after_a_scheduled_run(queue_client, add_machines, queue_settings):
    fleet(add_machines, queue_settings)
    add_schedule(queue_settings, created=BERLIN_2AM_UTC, retention="last=1")
    first = schedules.run_now(settings=queue_settings, name="nightly")
    wait_done(queue_client, first)
    wait_until(lambda: _has_backup(queue_settings, first))
    second = schedules.run_now(settings=queue_settings, name="nightly")
    wait_done(queue_client, second)
    # The newer backup stays, the older is pruned once the newer is stored.
    wait_until(lambda: _has_backup(queue_settings, second)
               and not _has_backup(queue_settings, first))
    assert backups_count(queue_settings) == 1
    kept = list((queue_settings.data_dir / "backups").glob("*.zip"))
    assert len(kept) == 1


def test_a_failed_scheduled_backup_never_prunes_the_last_one_that_holds_files(
        queue_client, add_machines, queue_settings):
    fleet(add_machines, queue_settings)
    add_schedule(queue_settings, created=BERLIN_2AM_UTC, retention="last=1")
    good = schedules.run_now(settings=queue_settings, name="nightly")
    wait_done(queue_client, good)
    wait_until(lambda: _has_backup(queue_settings, good))
    options = queue_settings.data_dir / "mock" / "a1" / "options.json"
    options.write_text('{"offline": true}')  # the fleet is off for the next nights

    for _ in range(2):
        failed = schedules.run_now(settings=queue_settings, name="nightly")
        wait_done(queue_client, failed, timeout_s=90)
        wait_until(lambda: _has_backup(queue_settings, failed))  # noqa: B023
        follow_up.prune(settings=queue_settings, schedule_name="nightly")

    assert _has_backup(queue_settings, good)  # the one with the files stays
    with db.session_scope(queue_settings.resolved_database_url) as session:
        statuses = sorted(b.status.value for b in session.scalars(select(Backup)))
    assert statuses == ["complete", "failed"]  # the older failed one went


def _stored(session: Any, job_id: str, at: datetime, **machines: MachineBackupStatus) -> None:
    """A backup of schedule "nightly" as its assembly registers it, each machine's state
    given (its files are not needed to prune it)."""
    states = set(machines.values())
    status = (BackupStatus.COMPLETE if states == {MachineBackupStatus.OK} else
              BackupStatus.FAILED if states == {MachineBackupStatus.FAILED} else
              BackupStatus.PARTIAL)
    session.add(Backup(id=job_id, job_id=job_id, name=f"{job_id}.zip", status=status,
                       created_at=at, machines=[
                           BackupMachine(position=i, machine_id=m, machine_name=m, status=s)
                           for i, (m, s) in enumerate(machines.items())]))
    session.add(ScheduleRun(schedule_name="nightly", fire_at=at, job_id=job_id))


def test_retention_keeps_the_last_good_copy_of_a_machine_that_was_off(settings):
    ok, off = MachineBackupStatus.OK, MachineBackupStatus.FAILED
    add_schedule(settings, created=BERLIN_2AM_UTC, retention="last=2")
    with db.session_scope(settings.resolved_database_url) as session:
        for night, (a1, a2) in enumerate([(ok, ok), (ok, ok), (ok, off), (ok, off)]):
            _stored(session, f"night{night}", BERLIN_2AM_UTC + timedelta(days=night),
                    a1=a1, a2=a2)

    pruned = follow_up.prune(settings=settings, schedule_name="nightly")

    assert pruned == ["night0.zip"]  # night1, a2's last copy, stays beside the last two


def _four_nights(settings: Any) -> Any:
    """Schedule "nightly" keeping the last two of four stored backups, each with its ZIP."""
    add_schedule(settings, created=BERLIN_2AM_UTC, retention="last=2")
    ok = MachineBackupStatus.OK
    with db.session_scope(settings.resolved_database_url) as session:
        for night in range(4):
            _stored(session, f"night{night}", BERLIN_2AM_UTC + timedelta(days=night), a1=ok)
    folder = settings.data_dir / "backups"
    folder.mkdir(parents=True, exist_ok=True)
    for night in range(4):
        (folder / f"night{night}.zip").write_bytes(b"PK")
    return folder


def test_a_prune_whose_commit_fails_keeps_the_zips_of_the_backups_still_listed(
        settings, monkeypatch):
    folder = _four_nights(settings)

    def lost(self: Any) -> None:
        raise OperationalError("COMMIT", {}, Exception("server closed the connection"))

    with monkeypatch.context() as patched:
        patched.setattr(Session, "commit", lost)
        with pytest.raises(OperationalError):
            follow_up.prune(settings=settings, schedule_name="nightly")

    assert backups_count(settings) == 4
    assert sorted(p.name for p in folder.glob("*.zip")) == [
        "night0.zip", "night1.zip", "night2.zip", "night3.zip"]


def test_a_zip_that_cannot_be_removed_does_not_stop_the_prune(settings):
    folder = _four_nights(settings)
    (folder / "night0.zip").unlink()
    (folder / "night0.zip").mkdir()  # a name unlink() refuses (IsADirectoryError)

    pruned = follow_up.prune(settings=settings, schedule_name="nightly")

    assert pruned == ["night0.zip", "night1.zip"]
    assert backups_count(settings) == 2
    assert not (folder / "night1.zip").exists()


def _has_backup(settings: Any, job_id: str) -> bool:
    with db.session_scope(settings.resolved_database_url) as session:
        return session.scalar(select(Backup.id).where(Backup.job_id == job_id)) is not None


def test_a_partial_scheduled_backup_sends_an_alert_saying_why_in_the_machines_own_words(
        queue_client, add_machines, queue_settings, alerts):
    fleet(add_machines, queue_settings)
    add_machines({"id": "z9", "name": "Off", "model": "Mock", "options": {"offline": True}})
    add_schedule(queue_settings, created=BERLIN_2AM_UTC)
    job_id = schedules.run_now(settings=queue_settings, name="nightly")
    wait_done(queue_client, job_id, timeout_s=90)
    wait_until(lambda: bool(alerts.requests), timeout_s=30)
    alert = alerts.requests[0].json()
    assert "partial" in alert["title"]
    assert "z9: 20004 Machine is offline. - machine is offline (simulated)" in alert["body"]


def _partial_night(settings: Any, alerts: Any) -> Any:
    """Schedule "nightly" (keeping the last one) and its backup "night0", partial; the
    settings that send its alerts to `alerts`."""
    add_schedule(settings, created=BERLIN_2AM_UTC, retention="last=1")
    with db.session_scope(settings.resolved_database_url) as session:
        _stored(session, "night0", BERLIN_2AM_UTC, a1=MachineBackupStatus.OK,
                a2=MachineBackupStatus.FAILED)
    return settings.model_copy(update={"notify_urls": [alerts.url()]})


def test_a_retention_pass_that_fails_does_not_stop_the_scheduled_backups_alert(
        settings, alerts, monkeypatch):
    alerting = _partial_night(settings, alerts)

    def refused(**_: Any) -> list[str]:
        raise PermissionError(13, "Permission denied", "backups/night-before.zip")

    monkeypatch.setattr(follow_up, "prune", refused)
    follow_up.after_backup(settings=alerting, backup_id="night0")

    assert [a.json()["title"] for a in alerts.requests] == ["dncq: backup nightly is partial"]


def test_a_scheduled_backups_alert_is_sent_once_however_often_its_steps_are_asked(
        settings, alerts):
    alerting = _partial_night(settings, alerts)

    for _ in range(2):  # its assembly delivered twice
        follow_up.after_backup(settings=alerting, backup_id="night0")

    assert len(alerts.requests) == 1


def test_a_delivery_beside_one_that_is_alerting_sends_no_second_alert(
        settings, alerts, monkeypatch):
    alerting = _partial_night(settings, alerts)
    send = follow_up._alert

    def slow_webhook(*args: Any, **kwargs: Any) -> None:
        # the reaper's second delivery of a slow assembly asks while the first alerts
        monkeypatch.setattr(follow_up, "_alert", send)
        follow_up.after_backup(settings=alerting, backup_id="night0")
        send(*args, **kwargs)

    monkeypatch.setattr(follow_up, "_alert", slow_webhook)
    follow_up.after_backup(settings=alerting, backup_id="night0")

    assert len(alerts.requests) == 1


def test_an_assembly_delivered_again_after_its_worker_was_lost_sends_the_alert_owed(
        queue_client, add_machines, queue_settings, alerts, monkeypatch):
    fleet(add_machines, queue_settings)
    add_machines({"id": "z9", "name": "Off", "model": "Mock", "options": {"offline": True}})
    add_schedule(queue_settings, created=BERLIN_2AM_UTC)
    lost = threading.Event()

    def worker_lost(**_: Any) -> None:  # the backup is registered, nothing after it ran
        lost.set()
        raise RuntimeError("worker lost")

    monkeypatch.setattr(follow_up, "after_backup", worker_lost)
    job_id = schedules.run_now(settings=queue_settings, name="nightly")
    wait_done(queue_client, job_id, timeout_s=90)
    wait_until(lost.is_set)
    monkeypatch.undo()

    queue.enqueue_assembly(queue_settings, job_id)  # as the broker delivers it again

    wait_until(lambda: bool(alerts.requests))
    assert "partial" in alerts.requests[0].json()["title"]


def test_a_rollout_with_failed_targets_sends_an_alert(queue_client, add_machines, alerts):
    add_machines({"id": "a1", "name": "Lathe", "model": "Mock"})
    job = queue_client.post("/api/jobs", json={
        "kind": "delete", "targets": [{"machineID": "a1", "fileName": "missing.nc"}]}).json()
    wait_done(queue_client, job["id"])
    wait_until(lambda: bool(alerts.requests))
    assert job["id"] in alerts.requests[0].json()["title"]


@pytest.mark.parametrize(("body", "why"), [
    ({"cron": "0 0 31 2 *"}, "never fires"),  # 31 February
    ({"cron": "* * * * * *"}, "a cron of five fields"),  # seconds: a backup at every look
    ({"cron": "0 2 * * * 2030"}, "a cron of five fields"),
    ({"cron": "0 2 * *"}, "a cron of five fields"),
    ({"cron": "0 2 * * *", "machines": {}}, "no machine selected"),
    ({"cron": "0 2 * * *", "dirAtCNC": "../.."}, "leaves the machine's root"),
    ({"cron": "0 2 * * *", "dirAtCNC": "PRG\\..\\.."}, "leaves the machine's root"),
    ({"cron": "0 2 * * *", "notify": ["not a url"]}, "notify[0]: not a URL"),
    ({"cron": "0 2 * * *", "notify": ["https://"]}, "notify[0]: a https:// URL needs a host"),
])
def test_a_schedule_that_could_never_back_anything_up_is_refused(client, body, why):
    response = client.post("/api/schedules", json={"name": "never", **body})
    assert response.status_code == 400
    assert response.json()["errorCode"] == 20001 and why in response.json()["statusMsg"]
    assert client.get("/api/schedules").json() == []


def test_a_schedule_whose_folder_is_outside_its_machines_roots_is_refused_naming_them(
        client, add_machines):
    add_machines({"id": "d1", "name": "Drill", "model": "Delta"},
                 {"id": "f1", "name": "Mill", "model": "Fanuc 0i-F"},
                 {"id": "m1", "name": "Lathe", "model": "Mock"})  # its root holds any folder

    answer = client.post("/api/schedules", json={"name": "etc", "cron": "0 2 * * *",
                                                 "dirAtCNC": "/etc"})

    assert answer.status_code == 422 and answer.json()["errorCode"] == 20002
    assert answer.json()["statusMsg"] == (
        "'/etc' is not below the roots of machine d1 (B:\\), "
        "machine f1 (//CNC_MEM/, //MEMCARD/); the schedule was not saved")
    assert client.get("/api/schedules").json() == []


def test_a_schedule_with_a_folder_for_a_machine_that_takes_no_folder_is_refused_naming_it(
        client, add_machines):
    add_machines({"id": "f1", "name": "Mill", "model": "Fanuc 0i-F"},
                 {"id": "f18", "name": "Lathe", "model": "Fanuc 18i"})  # one memory, no folders

    answer = client.post("/api/schedules", json={"name": "user", "cron": "0 2 * * *",
                                                 "dirAtCNC": "USER"})

    assert answer.status_code == 422 and answer.json()["errorCode"] == 20003
    assert answer.json()["statusMsg"] == (
        "machine f18: Fanuc (other models) takes no target folder; the schedule was not saved")
    assert client.get("/api/schedules").json() == []


def test_a_schedule_given_machines_its_saved_folder_is_outside_of_is_refused(
        client, add_machines):
    add_machines({"id": "d1", "name": "Drill", "model": "Delta"},
                 {"id": "f1", "name": "Mill", "model": "Fanuc 0i-F"})
    saved = client.post("/api/schedules", json={"name": "mills", "cron": "0 2 * * *",
                                                "machines": {"ids": ["f1"]},
                                                "dirAtCNC": "//CNC_MEM/PRG"})
    assert saved.status_code == 201

    # `dncq schedule add mills --cron ... --to d1`: the folder saved before stays
    answer = client.post("/api/schedules", json={"name": "mills", "cron": "0 2 * * *",
                                                 "machines": {"ids": ["d1"]}})

    assert answer.status_code == 422
    assert answer.json()["statusMsg"].startswith("'//CNC_MEM/PRG' is not below the roots "
                                                  "of machine d1")
    assert client.get("/api/schedules/mills").json()["machines"] == {
        "ids": ["f1"], "tags": [], "all": False}


def test_a_change_may_leave_out_the_cron_and_machines_a_new_schedule_needs_its_cron(
        client, add_machines):
    add_machines({"id": "d1", "name": "Drill", "model": "Delta"},
                 {"id": "f1", "name": "Mill", "model": "Fanuc 0i-F"})
    client.post("/api/schedules", json={"name": "mills", "cron": "0 2 * * *",
                                        "machines": {"ids": ["f1"]}})

    # its folder is checked against the machines it keeps (f1), not against every machine
    changed = client.post("/api/schedules", json={"name": "mills", "retention": "last=5",
                                                  "dirAtCNC": "//CNC_MEM/PRG"})
    new = client.post("/api/schedules", json={"name": "drills", "retention": "last=5"})
    nulled = client.post("/api/schedules", json={"name": "mills", "cron": None})
    named = client.post("/api/schedules", json={"name": "mills"})  # nothing to change

    assert changed.status_code == 201, changed.json()
    assert (changed.json()["cron"], changed.json()["machines"]["ids"],
            changed.json()["retention"]) == ("0 2 * * *", ["f1"], "last=5")
    assert new.status_code == 422 and new.json()["statusMsg"].startswith(
        "cron: a new schedule needs one")
    assert nulled.status_code == 400 and "leave it out" in nulled.json()["statusMsg"]
    assert named.status_code == 201 and named.json()["retention"] == "last=5"
    assert [s["name"] for s in client.get("/api/schedules").json()] == ["mills"]


def test_a_change_of_a_schedules_retention_alone_is_not_refused_for_its_folder(
        client, add_machines):
    add_machines({"id": "f1", "name": "Mill", "model": "Fanuc 0i-F"})
    client.post("/api/schedules", json={"name": "all", "cron": "0 2 * * *",
                                        "dirAtCNC": "//CNC_MEM/PRG"})
    add_machines({"id": "d1", "name": "Drill", "model": "Delta"})  # its root lacks the folder

    changed = client.post("/api/schedules", json={"name": "all", "retention": "last=5"})

    assert changed.status_code == 201, changed.json()
    assert changed.json()["retention"] == "last=5"


def test_schedules_api_adds_lists_and_removes(client, demo_fleet):
    created = client.post("/api/schedules", json={
        "name": "nightly", "cron": "30 1 * * *", "timezone": "Europe/Berlin",
        "machines": {"tags": ["lathes"]}, "retention": "daily=7",
        "notify": ["https://user:secret@hooks.example/x"]})
    assert created.status_code == 201
    listed = client.get("/api/schedules").json()
    assert [s["name"] for s in listed] == ["nightly"]
    assert "secret" not in str(listed)
    assert client.post("/api/schedules", json={"name": "bad", "cron": "every night"}
                       ).status_code == 400
    assert client.delete("/api/schedules/nightly").status_code == 204
    assert client.get("/api/schedules").json() == []


HOOK = "https://hooks.example/services/T0/B0/tok3n-in-its-path?key=s3cr3t"


def test_a_schedules_alert_urls_are_sealed_in_the_database_and_still_alert_there(
        client, demo_fleet, settings):
    assert client.post("/api/schedules", json={
        "name": "nightly", "cron": "30 1 * * *", "notify": [HOOK]}).status_code == 201

    with db.session_scope(settings.resolved_database_url) as session:
        stored = session.execute(text("SELECT notify FROM schedules")).scalar_one()
        schedule = schedules.get(session=session, name="nightly")
        told = follow_up.alert_urls(settings, schedule)
    assert "hooks.example" not in str(stored) and "s3cr3t" not in str(stored)
    assert told == [*settings.notify_urls, HOOK]


@pytest.mark.parametrize("sealed_by", ["this dncq's key", "another key"])
def test_an_alert_url_given_already_sealed_is_refused_and_the_schedule_not_saved(
        client, demo_fleet, settings, sealed_by):
    keys = (sealed.keyring(settings.data_dir) if sealed_by == "this dncq's key"
            else sealed.Keyring([sealed.new_key()], source="another dncq"))

    answer = client.post("/api/schedules", json={
        "name": "nightly", "cron": "30 1 * * *", "notify": [HOOK, keys.seal(HOOK)]})

    assert answer.status_code == 400 and answer.json()["errorCode"] == 20001
    assert answer.json()["statusMsg"] == (
        "notify: notify[1]: dncq-sealed:v1:… is how dncq stores an alert URL, not one it "
        "takes: give the URL itself")
    assert client.get("/api/schedules").json() == []


def test_alert_urls_stored_in_clear_by_an_earlier_version_are_sealed_by_reseal(
        client, demo_fleet, settings):
    client.post("/api/schedules", json={"name": "nightly", "cron": "30 1 * * *"})
    with db.session_scope(settings.resolved_database_url) as session:
        session.execute(update(Schedule).values(notify=[HOOK]))  # as stored before sealing
        assert schedules.reseal(session=session, data_dir=settings.data_dir) == 1

    with db.session_scope(settings.resolved_database_url) as session:
        stored = session.execute(text("SELECT notify FROM schedules")).scalar_one()
        schedule = schedules.get(session=session, name="nightly")
        assert "hooks.example" not in str(stored)
        assert follow_up.alert_urls(settings, schedule) == [*settings.notify_urls, HOOK]


def fires_between(cron: str, start: datetime, end: datetime) -> list[str]:
    """Berlin wall-clock times a schedule fires at, ticking every five minutes."""
    berlin = ZoneInfo("Europe/Berlin")
    schedule = Schedule(name="s", cron=cron, timezone="Europe/Berlin", created_at=start)
    fired, last, now = [], None, start
    while now < end:
        if fire := schedules.due_fire(schedule, last, now):
            fired.append(fire.astimezone(berlin).strftime("%d %H:%M%z"))
            last = fire
        now += timedelta(minutes=5)
    return fired


# Europe/Berlin in 2026: on 29 March 02:00 CET becomes 03:00 CEST (no 02:xx that night);
# on 25 October 03:00 CEST becomes 02:00 CET (02:xx twice).


def test_a_nightly_schedule_fires_once_on_the_night_the_clocks_go_back():
    fired = fires_between("0 2 * * *", datetime(2026, 10, 23, 12, tzinfo=UTC),
                          datetime(2026, 10, 27, 12, tzinfo=UTC))
    assert fired == ["24 02:00+0200", "25 02:00+0200", "26 02:00+0100", "27 02:00+0100"]


def test_a_nightly_schedule_in_the_hour_the_clocks_skip_fires_right_after_it():
    fired = fires_between("30 2 * * *", datetime(2026, 3, 27, 12, tzinfo=UTC),
                          datetime(2026, 3, 30, 12, tzinfo=UTC))
    assert fired == ["28 02:30+0100", "29 03:00+0200", "30 02:30+0200"]


def test_an_hourly_schedule_also_fires_in_the_repeated_hour():
    fired = fires_between("0 * * * *", datetime(2026, 10, 24, 22, 30, tzinfo=UTC),
                          datetime(2026, 10, 25, 3, 30, tzinfo=UTC))
    assert fired == ["25 01:00+0200", "25 02:00+0200", "25 02:00+0100", "25 03:00+0100",
                     "25 04:00+0100"]


def test_the_last_run_is_shown_in_the_schedules_zone_as_the_next_one_is(settings):
    with db.session_scope(settings.resolved_database_url) as session:
        schedule = schedules.upsert(
            session=session, data_dir=settings.data_dir, schedule_in=schedules.ScheduleIn(
                name="nightly", cron="0 2 * * *", timezone="Europe/Berlin"))
        session.add(ScheduleRun(schedule_name="nightly",
                                fire_at=datetime(2026, 11, 25, 1, 0, tzinfo=UTC)))
        session.flush()
        shown = schedules.view(session, schedule, now=datetime(2026, 11, 25, 1, 5, tzinfo=UTC))
    assert shown["lastRun"].strftime("%d %H:%M%z") == "25 02:00+0100"  # 01:00 UTC
    assert shown["nextRun"].strftime("%d %H:%M%z") == "26 02:00+0100"


def test_the_next_run_shown_skips_the_repeated_hour(settings):
    with db.session_scope(settings.resolved_database_url) as session:
        schedule = schedules.upsert(
            session=session, data_dir=settings.data_dir, schedule_in=schedules.ScheduleIn(
                name="nightly", cron="0 2 * * *", timezone="Europe/Berlin"))
        first_pass = datetime(2026, 10, 25, 0, 30, tzinfo=UTC)  # 02:30 CEST, first pass
        shown = schedules.view(session, schedule, now=first_pass)
    assert shown["nextRun"].strftime("%d %H:%M%z") == "26 02:00+0100"


def test_a_schedule_of_a_folder_nested_past_500_characters_is_kept_whole(database_url,
                                                                         tmp_path):
    folder = "/".join("F" * 99 for _ in range(7))  # 699 characters, a path dncq takes
    with db.session_scope(database_url) as session:
        schedules.upsert(session=session, data_dir=tmp_path, schedule_in=schedules.ScheduleIn(
            name="deep", cron="0 2 * * *", machines={"all": True}, dirAtCNC=folder))
    with db.session_scope(database_url) as session:
        assert schedules.get(session=session, name="deep").dir_at_cnc == folder


def test_a_schedules_time_zone_is_known_without_the_systems_time_zone_files():
    # A slim container image or Windows has no /usr/share/zoneinfo (or lacks the legacy
    # names such as US/Central); the zones then come with dncq itself.
    zoneinfo.reset_tzpath(to=[])
    zoneinfo.ZoneInfo.clear_cache()
    try:
        for zone in ("Europe/Berlin", "US/Central"):
            assert schedules.ScheduleIn(name="nightly", cron="0 2 * * *", timezone=zone)
    finally:
        zoneinfo.reset_tzpath()
        zoneinfo.ZoneInfo.clear_cache()
