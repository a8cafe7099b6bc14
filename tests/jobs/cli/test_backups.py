"""`dncq backup ...` and `dncq schedule ...` against a live API and worker."""

from __future__ import annotations

import re
import time
from datetime import UTC, datetime

import httpx
from sqlalchemy import update

from jobs import db, schedules
from jobs.backup_models import Backup, ScheduleRun
from tests.conftest import API_KEY
from tests.jobs.cli.runner import dncq, table_rows
from tests.jobs.helpers import on_machine


def backup_ids(output: str) -> list[str]:
    return re.findall(r"Backup ([0-9a-f]{16}):", output)


def test_backup_run_list_verify_diff_and_restore(live_with_worker, queue_settings):
    on_machine(queue_settings, "m0", "P1.nc").write_text("G0 X1\n")
    on_machine(queue_settings, "m0", "sub/P2.nc").write_text("G0 X2\n")
    first = dncq("backup", "run", "--to", "m0,m1")
    assert first.exit_code == 0, first.output
    [first_id] = backup_ids(first.output)
    [listed] = table_rows(dncq("backup", "list").output)  # in 80 columns
    assert (listed["id"], listed["status"], listed["machines"]) == (first_id, "complete", "2/2")
    assert "is sound" in dncq("backup", "verify", first_id).output

    on_machine(queue_settings, "m0", "P1.nc").write_text("G0 X100\n")
    [second_id] = backup_ids(dncq("backup", "run", "--to", "m0,m1").output)
    changed = dncq("backup", "diff", first_id, second_id)
    assert "~ /P1.nc" in changed.output

    restored = dncq("backup", "restore", first_id, "--machine", "m0", "--path", "/sub",
                    "--to", "m2")
    assert restored.exit_code == 0, restored.output
    assert re.search(r"Restore job [0-9a-f]+: 1 file\.", restored.output)
    assert on_machine(queue_settings, "m2", "sub/P2.nc").read_text() == "G0 X2\n"


def test_backup_restore_takes_a_fanuc_path_as_backup_show_names_it(
        live_with_worker, add_machines, tmp_path):
    add_machines({"id": "f0i", "name": "Lathe", "model": "Fanuc 0i-F"})
    program = tmp_path / "part.nc"
    program.write_text("%\nO1234\nG0 X1\nM30\n%\n")
    assert dncq("put", "f0i", str(program)).exit_code == 0
    [backup_id] = backup_ids(dncq("backup", "run", "--to", "f0i").output)
    assert "O1234" in dncq("backup", "show", backup_id).output

    restored = dncq("backup", "restore", backup_id, "--machine", "f0i", "--path", "O1234",
                    "--replace")
    mistyped = dncq("backup", "restore", backup_id, "--machine", "f0i", "--path", "O1235")

    assert restored.exit_code == 0, restored.output
    assert mistyped.exit_code != 0
    assert "holds nothing of f0i at O1235 (did you mean O1234?)" in mistyped.output


def test_backup_diff_names_the_backup_that_holds_only_part_of_a_machine(
        live_with_worker, queue_settings):
    on_machine(queue_settings, "m0", "P1.nc").write_text("G0 X1\n")
    [whole_id] = backup_ids(dncq("backup", "run", "--to", "m0").output)
    on_machine(queue_settings, "m0", "P1.nc").rename(
        on_machine(queue_settings, "m0", "P1.nc").with_name("bad\udcffname.nc"))
    [part_id] = backup_ids(dncq("backup", "run", "--to", "m0").output)  # leaves bad\xff out

    compared = dncq("backup", "diff", whole_id, part_id)

    assert compared.exit_code == 0, compared.output
    assert f"backup {part_id} holds only some of its files (partial)" in compared.output
    assert "No differences." not in compared.output
    assert "No differences in the files both backups hold." in compared.output
    for pair in ((whole_id, part_id), (whole_id, whole_id)):
        mistyped = dncq("backup", "diff", *pair, "--machine", "mO")  # not m0
        assert "neither backup holds machine mO" in mistyped.output
        assert "No differences" not in mistyped.output


def test_backup_verify_of_a_corrupted_zip_exits_1(live_with_worker, queue_settings):
    on_machine(queue_settings, "m0", "P1.nc").write_text("G0 X1\n" * 100)
    [backup_id] = backup_ids(dncq("backup", "run", "--to", "m0").output)
    [zip_path] = (queue_settings.data_dir / "backups").glob("*.zip")
    zip_path.write_bytes(zip_path.read_bytes()[:-40])  # the central directory cut short
    result = dncq("backup", "verify", backup_id)
    assert result.exit_code == 1


def test_backup_show_says_why_a_machine_failed_in_its_own_words(live_with_worker, add_machines):
    add_machines({"id": "z9", "name": "Off", "model": "Mock", "options": {"offline": True}})
    run = dncq("backup", "run", "--to", "m0,z9")
    [backup_id] = backup_ids(run.output)

    shown = dncq("backup", "show", backup_id)

    assert shown.exit_code == 0, shown.output
    assert "z9 Off: failed (20004 Machine is offline. - machine is offline (simulated))" \
        in shown.output


def test_backup_run_with_a_machine_offline_says_once_the_backup_is_partial_without_it(
        live_with_worker, add_machines):
    add_machines({"id": "z9", "name": "Off", "model": "Mock", "options": {"offline": True}})

    run = dncq("backup", "run", "--to", "m0,m1,z9")

    assert run.exit_code == 1  # a machine failed, as for every command that follows a job
    job_id = re.search(r"Backup job (\w+):", run.output)[1]
    assert re.search(rf"^job {job_id} \(backup\)$", run.output, re.M), run.output  # not failed
    assert re.search(r"^Backup \w+: \S+\.zip, partial \(z9 failed\), \d+ files, \d+ bytes\.$",
                     run.output, re.M), run.output


def test_schedule_add_list_run_now_and_rm(live_with_worker):
    added = dncq("schedule", "add", "nightly", "--cron", "0 2 * * *", "--tz", "Europe/Berlin",
                 "--tag", "lathes", "--keep", "last=2")
    assert added.exit_code == 0, added.output
    listed = dncq("schedule", "list")
    assert "nightly" in listed.output and "#lathes" in listed.output
    started = dncq("schedule", "run-now", "nightly")
    assert started.exit_code == 0 and "Backup job" in started.output
    assert dncq("schedule", "rm", "nightly").exit_code == 0
    assert "nightly" not in dncq("schedule", "list").output


def test_a_schedule_disabled_lists_as_paused_until_enabled(live_with_worker):
    dncq("schedule", "add", "nightly", "--cron", "0 2 * * *", "--all")

    disabled = dncq("schedule", "disable", "nightly")
    paused = table_rows(dncq("schedule", "list").output)
    enabled = dncq("schedule", "enable", "nightly")
    resumed = table_rows(dncq("schedule", "list").output)

    assert disabled.exit_code == 0 and enabled.exit_code == 0, disabled.output + enabled.output
    assert paused[0]["next run"] == "paused"
    assert re.fullmatch(r"\d{4}-\d\d-\d\d 02:00", resumed[0]["next run"])
    assert dncq("schedule", "disable", "nope").exit_code == 1


def test_schedule_list_says_which_pass_of_the_repeated_hour_the_runs_are(
        elsewhere, settings, add_machines, monkeypatch):
    # Berlin, 25 October 2026, 02:10 CET: the hourly backup of 02:00 summer time ran, the
    # clocks went back to 02:00, and the next one is 02:00 winter time.
    add_machines({"id": "m0", "name": "M0", "model": "Mock"})
    dncq("schedule", "add", "hourly", "--cron", "0 * * * *", "--tz", "Europe/Berlin", "--all")
    schedules.run_now(settings=settings, name="hourly")
    with db.session_scope(settings.resolved_database_url) as session:
        session.execute(update(ScheduleRun).values(
            fire_at=datetime(2026, 10, 25, 0, 0, tzinfo=UTC)))
    monkeypatch.setattr(schedules, "utcnow", lambda: datetime(2026, 10, 25, 0, 10, tzinfo=UTC))

    [row] = table_rows(dncq("schedule", "list", width=200).output)

    assert (row["next run"], row["last run"]) == ("2026-10-25 02:00 CET",
                                                  "2026-10-25 02:00 CEST")


def test_schedule_add_over_a_schedule_changes_what_it_gives_and_keeps_the_rest(
        live_with_worker):
    dncq("schedule", "add", "nightly", "--cron", "0 2 * * *", "--tz", "Europe/Berlin",
         "--all", "--keep", "last=3", "--notify", "https://hooks.example/dncq")
    dncq("schedule", "disable", "nightly")

    changed = dncq("schedule", "add", "nightly", "--cron", "30 3 * * *", "--tag", "lathes")

    assert changed.exit_code == 0, changed.output
    assert "paused" in changed.output
    [row] = table_rows(dncq("schedule", "list", width=200).output)
    assert (row["cron"], row["zone"], row["machines"], row["retention"], row["next run"]) == (
        "30 3 * * *", "Europe/Berlin", "#lathes", "last=3", "paused")
    shown = httpx.get(f"{live_with_worker.url}/api/schedules/nightly",
                      headers={"X-Api-Key": API_KEY}).json()
    assert shown["notify"] == 1  # the alert URL, which is never shown back, stays


def test_schedule_add_of_a_schedule_that_exists_may_give_only_what_changes(live_with_worker):
    dncq("schedule", "add", "nightly", "--cron", "0 2 * * *", "--tag", "lathes")

    changed = dncq("schedule", "add", "nightly", "--keep", "last=5")
    new = dncq("schedule", "add", "weekly", "--keep", "last=5", "--cron", "0 3 * * 0")

    assert changed.exit_code == 0, changed.output
    [row] = table_rows(dncq("schedule", "list", width=200).output)
    assert (row["cron"], row["machines"], row["retention"]) == ("0 2 * * *", "#lathes", "last=5")
    # a new schedule still says where: the API's every machine is not assumed
    assert new.exit_code == 2 and "say where" in new.output
    bare = dncq("schedule", "add", "monthly")
    assert bare.exit_code == 2 and "a new schedule needs --cron and where" in bare.output


def test_schedule_list_says_the_zone_of_its_times_whole(live_with_worker):
    added = dncq("schedule", "add", "nightly", "--cron", "0 2 * * 1-5", "--all",
                 "--tz", "America/Argentina/Buenos_Aires", "--keep", "last=2,daily=14,weekly=8")

    listed = dncq("schedule", "list").output
    row = table_rows(listed)[0]

    assert re.search(r"next run \d{4}-\d\d-\d\d 02:00 America/Argentina/Buenos_Aires\.$",
                     added.output.strip()), added.output
    assert row["next run"].endswith(" 02:00")
    assert " 0 2 * * 1-5 " in listed  # whole on its line: a cron over two lines reads as two
    assert row["zone"].replace(" ", "") == "America/Argentina/Buenos_Aires"  # folded, not cut
    assert row["retention"].replace(" ", "") == "last=2,daily=14,weekly=8"


def test_schedule_add_with_a_bad_cron_fails(live_with_worker):
    result = dncq("schedule", "add", "x", "--cron", "sometimes", "--all")
    assert result.exit_code == 1 and "cron" in result.output


def test_ctrl_c_before_dncq_answers_a_backup_restore_says_the_restore_may_be_queued(
        live_with_worker, queue_settings, ctrl_c_before_the_answer):
    on_machine(queue_settings, "m0", "P1.nc").write_text("G0 X1\n")
    [backup_id] = backup_ids(dncq("backup", "run", "--to", "m0").output)
    ctrl_c_before_the_answer("/restore")

    result = dncq("backup", "restore", backup_id, "--machine", "m0", "--to", "m1")

    assert result.exit_code == 130
    assert ("Stopped before dncq answered. If it had the whole request, the restore job was "
            "queued all the same: dncq jobs --kind restore shows it, and dncq cancel JOB") \
        in " ".join(result.output.split())
    assert [row["kind"] for row in table_rows(dncq("jobs", "--kind", "restore").output)] == [
        "restore"]


def test_ctrl_c_before_dncq_answers_a_schedule_run_now_says_the_backup_may_have_started(
        live_with_worker, ctrl_c_before_the_answer):
    dncq("schedule", "add", "nightly", "--cron", "0 2 * * *", "--to", "m0")
    ctrl_c_before_the_answer("/run")

    result = dncq("schedule", "run-now", "nightly")

    assert result.exit_code == 130
    assert ("Stopped before dncq answered. If it had the whole request, the backup of "
            "schedule nightly was started all the same: dncq jobs --kind backup shows it") \
        in " ".join(result.output.split())
    assert [row["kind"] for row in table_rows(dncq("jobs", "--kind", "backup").output)] == [
        "backup"]


def test_ctrl_c_before_dncq_answers_a_schedule_rm_says_it_may_be_removed_all_the_same(
        live_with_worker, ctrl_c_before_the_answer):
    # Any change (a schedule removed, a user added, a version approved) ended on a bare ^C.
    dncq("schedule", "add", "nightly", "--cron", "0 2 * * *", "--to", "m0")
    ctrl_c_before_the_answer("/nightly", method="DELETE")

    result = dncq("schedule", "rm", "nightly")

    assert result.exit_code == 130
    assert ("Stopped before dncq answered. If it had the whole request, the change was made "
            "all the same: list or show what it changed to check.") \
        in " ".join(result.output.split())
    assert "nightly" not in dncq("schedule", "list").output


def test_ctrl_c_while_reading_ends_with_no_word_of_a_change(
        live_with_worker, ctrl_c_before_the_answer):
    dncq("schedule", "add", "nightly", "--cron", "0 2 * * *", "--to", "m0")
    ctrl_c_before_the_answer("/schedules", method="GET")

    result = dncq("schedule", "list")

    assert result.exit_code != 0 and "Stopped before dncq answered" not in result.output


def test_job_watch_of_a_backup_ends_with_its_verdict_as_backup_run_does(
        live_with_worker, add_machines):
    # After a Ctrl-C in `backup run`, following the job again showed its targets and no ZIP.
    add_machines({"id": "z9", "name": "Off", "model": "Mock", "options": {"offline": True}})
    queued = dncq("backup", "run", "--to", "m0,z9", "--no-wait")
    job_id = re.search(r"Backup job (\w+):", queued.output)[1]

    watched = dncq("job", job_id, "--watch")

    assert watched.exit_code == 1  # a machine failed, as `backup run` says it
    assert re.search(rf"^job {job_id} \(backup\)$", watched.output, re.M), watched.output
    assert re.search(r"^Backup \w+: \S+\.zip, partial \(z9 failed\), \d+ files?, \d+ bytes\.$",
                     watched.output, re.M), watched.output


def test_ctrl_c_while_backup_run_waits_for_the_zip_says_it_is_stored_all_the_same(
        live_with_worker, ctrl_c_before_the_answer):
    ctrl_c_before_the_answer("/api/backups", method="GET")

    run = dncq("backup", "run", "--to", "m0")

    job_id = re.search(r"Backup job (\w+):", run.output)[1]
    assert run.exit_code == 130
    assert ("Stopped waiting for the backup's ZIP; dncq stores it all the same: dncq backup "
            f"list shows it, and dncq job {job_id} --watch waits for it again.") in \
        " ".join(run.output.split())
    assert backup_ids(dncq("job", job_id, "--watch").output)


def test_backup_list_tells_two_backups_of_the_repeated_hour_apart_by_their_zone(
        live_with_worker, settings, monkeypatch):
    # Berlin, 25 October 2026: backups at 00:30 and 01:30 UTC both read 02:30, the clocks
    # having gone back in between.
    first, second = (backup_ids(dncq("backup", "run", "--to", "m0").output)[0]
                     for _ in range(2))
    with db.session_scope(settings.resolved_database_url) as session:
        for backup_id, hour in ((first, 0), (second, 1)):
            session.execute(update(Backup).where(Backup.id == backup_id).values(
                created_at=datetime(2026, 10, 25, hour, 30, tzinfo=UTC)))
    monkeypatch.setenv("TZ", "Europe/Berlin")
    time.tzset()
    try:
        listed = dncq("backup", "list")  # in 80 columns
        shown = dncq("backup", "show", first)
    finally:
        monkeypatch.undo()
        time.tzset()

    assert [(row["id"], row["created"]) for row in table_rows(listed.output)] == [
        (second, "2026-10-25 02:30 CET"), (first, "2026-10-25 02:30 CEST")]
    assert "2026-10-25 02:30:00 CEST)" in shown.output
