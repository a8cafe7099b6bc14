"""`dncq send|delete|jobs|job|retry|cancel|restore-replaced` against a live API and worker."""

from __future__ import annotations

import re
import time

import pytest

from jobs.api.app import create_app
from jobs.cli.client import Client
from jobs.cli.common import local_time
from jobs.settings import get_settings
from tests.jobs.cli.runner import PROGRAM, dncq, table_rows
from tests.jobs.helpers import on_machine, wait_until
from tests.live_server import serving


def test_send_to_a_tag_and_wait_puts_the_file_on_those_machines(
        live_with_worker, queue_settings, program):
    result = dncq("send", str(program), "--tag", "lathes", "--wait")
    assert result.exit_code == 0, result.output
    assert "2 succeeded" in result.output
    assert on_machine(queue_settings, "m0", "P.nc").read_text() == PROGRAM
    assert not on_machine(queue_settings, "m2", "P.nc").exists()


def test_send_exits_1_and_shows_142_when_a_target_fails(live_with_worker, queue_settings, program):
    on_machine(queue_settings, "m1", "P.nc").write_text("old")
    result = dncq("send", str(program), "--to", "m0,m1", "--wait")
    assert result.exit_code == 1
    assert "142" in result.output and "Path exists." in result.output
    states = [row["state"] for row in table_rows(result.output) if row["#"].isdigit()]
    assert states == ["succeeded", "failed"]  # plain words in the results table, no markup
    assert on_machine(queue_settings, "m1", "P.nc").read_text() == "old"


def test_replace_on_all_machines_asks_first_and_does_nothing_when_refused(
        live_with_worker, queue_settings, program):
    result = dncq("send", str(program), "--all", "--replace", answer="n\n")
    assert result.exit_code == 1
    assert "EVERY machine" in result.output
    assert not any(on_machine(queue_settings, f"m{i}", "P.nc").exists() for i in range(3))


def test_delete_on_all_machines_with_yes_does_not_ask(live_with_worker, queue_settings, program):
    for i in range(3):
        on_machine(queue_settings, f"m{i}", "P.nc").write_text(PROGRAM)
    result = dncq("delete", "P.nc", "--all", "--yes", "--wait")
    assert result.exit_code == 0, result.output
    assert not any(on_machine(queue_settings, f"m{i}", "P.nc").exists() for i in range(3))


def test_dry_run_prints_the_plan_and_sends_nothing(live_with_worker, queue_settings, program):
    on_machine(queue_settings, "m1", "P.nc").write_text("old")
    result = dncq("send", str(program), "--all", "--dry-run")
    assert result.exit_code == 0, result.output
    assert "send as P.nc" in result.output and "142" in result.output
    assert not on_machine(queue_settings, "m0", "P.nc").exists()


def test_a_name_with_colons_is_shown_as_given_not_as_an_emoji(live_with_worker, program):
    # Rich read `:100:` as the code of an emoji: the plan showed FIX💯.nc.
    result = dncq("send", str(program), "--to", "m0", "--name", "FIX:100:.nc", "--dry-run")

    assert [row["file"] for row in table_rows(result.output)] == ["FIX:100:.nc"]


def test_send_of_a_file_too_large_for_a_request_says_how_to_send_it(
        live_with_worker, queue_settings, program, monkeypatch):
    # A 40 MB program was refused with "request body over 20971520 bytes" and no way on.
    program.write_text(PROGRAM * 100)  # 2.4 KB, 3.2 KB as Base64
    small = queue_settings.model_copy(update={"max_json_body_bytes": 2048})
    with serving(create_app(small)) as server:
        monkeypatch.setenv("DNCQ_URL", server.url)
        get_settings.cache_clear()
        result = dncq("send", str(program), "--to", "m0")

    assert result.exit_code == 1
    said = " ".join(result.output.split())
    assert "20013" in said and "dncq library add FILE --folder FOLDER --approve" in said
    assert "--library FOLDER/NAME" in said
    assert not on_machine(queue_settings, "m0", "P.nc").exists()


def test_a_target_waiting_for_an_offline_machine_shows_why(live_with_worker, queue_settings,
                                                          program):
    options = queue_settings.data_dir / "mock" / "m1" / "options.json"
    options.parent.mkdir(parents=True, exist_ok=True)
    options.write_text('{"offline": true}')
    sent = dncq("send", str(program), "--to", "m1", "--deliver-within", "1h", "--no-wait")
    job_id = sent.output.split("Job ", 1)[1].split(":", 1)[0]

    wait_until(lambda: table_rows(dncq("job", job_id, width=200).output)[0]["message"]
               .startswith("waiting to retry after 20004 machine is offline"), timeout_s=20)
    options.unlink()  # switched on again: the next try delivers
    wait_until(lambda: on_machine(queue_settings, "m1", "P.nc").exists(), timeout_s=30)


def test_the_job_list_counts_failed_and_cancelled_targets_apart(
        live_with_worker, queue_settings, program):
    on_machine(queue_settings, "m0", "P.nc").write_text("old")  # 142 there: failed
    options = queue_settings.data_dir / "mock" / "m1" / "options.json"
    options.parent.mkdir(parents=True, exist_ok=True)
    options.write_text('{"offline": true}')  # waits there until cancelled
    sent = dncq("send", str(program), "--to", "m0,m1", "--deliver-within", "1h", "--no-wait")
    job_id = sent.output.split("Job ", 1)[1].split(":", 1)[0]
    wait_until(lambda: "142" in dncq("job", job_id).output, timeout_s=20)
    assert dncq("cancel", job_id).exit_code == 0

    # The job is cancelled at once; m1's attempt in flight ends cancelled when it returns.
    wait_until(lambda: table_rows(dncq("jobs").output)[0]["targets"].endswith("1 cancelled"),
               timeout_s=20)  # its cells wrapped in 80 columns
    [listed] = table_rows(dncq("jobs").output)  # this job alone, in 80 columns
    assert (listed["id"], listed["state"], listed["targets"]) == (
        job_id, "cancelled", "1 failed, 1 cancelled")  # each whole
    assert re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d \S+", listed["created"])


def test_times_are_shown_in_local_time_with_its_zone(monkeypatch):
    # What the API gives is UTC; --since and --until take local time, and so do the lists.
    monkeypatch.setenv("TZ", "Europe/Berlin")
    time.tzset()
    try:
        assert local_time("2026-12-06T02:40:11.250000Z") == "2026-12-06 03:40 CET"
        assert local_time("2026-07-01T23:59:59+00:00", seconds=True) == \
            "2026-07-02 01:59:59 CEST"
        assert local_time(None) == ""
    finally:
        monkeypatch.undo()
        time.tzset()


def test_a_zone_the_system_names_at_length_is_shown_as_its_offset(monkeypatch):
    # Windows names its zones in words (W. Europe Standard Time): a column of times that wide.
    monkeypatch.setenv("TZ", "WESTERNEUROPEANSTANDARD-1")
    time.tzset()
    try:
        assert local_time("2026-12-06T02:40:00Z") == "2026-12-06 03:40 +0100"
    finally:
        monkeypatch.undo()
        time.tzset()


def test_retry_after_fixing_the_cause_finishes_the_job(live_with_worker, queue_settings, program):
    blocker = on_machine(queue_settings, "m1", "P.nc")
    blocker.write_text("old")
    sent = dncq("send", str(program), "--to", "m0,m1", "--wait")
    job_id = sent.output.split("Job ", 1)[1].split(":", 1)[0]
    blocker.unlink()
    result = dncq("retry", job_id, "--wait")
    assert result.exit_code == 0, result.output
    assert on_machine(queue_settings, "m1", "P.nc").read_text() == PROGRAM
    shown = dncq("job", job_id)
    assert shown.exit_code == 0 and "succeeded" in shown.output
    listed = dncq("jobs", "--kind", "send")
    assert job_id in listed.output


def test_retry_of_a_job_with_nothing_to_retry_says_so(live_with_worker, program):
    sent = dncq("send", str(program), "--to", "m0", "--wait")
    job_id = sent.output.split("Job ", 1)[1].split(":", 1)[0]

    result = dncq("retry", job_id)

    assert result.exit_code == 0, result.output
    assert result.output.strip() == f"Nothing to retry: job {job_id} has no failed or " \
        "cancelled target."


def test_restore_replaced_puts_the_old_file_back(live_with_worker, queue_settings, program):
    target = on_machine(queue_settings, "m0", "P.nc")
    target.write_text("old\n")
    sent = dncq("send", str(program), "--to", "m0", "--replace", "--wait")
    assert sent.exit_code == 0, sent.output
    assert target.read_text() == PROGRAM
    job_id = sent.output.split("Job ", 1)[1].split(":", 1)[0]
    restored = dncq("restore-replaced", job_id)
    assert restored.exit_code == 0, restored.output
    assert target.read_text() == "old\n"


def test_restore_replaced_is_listed_as_a_restore_job(live_with_worker, queue_settings, program):
    on_machine(queue_settings, "m0", "P.nc").write_text("old\n")
    sent = dncq("send", str(program), "--to", "m0", "--replace", "--wait")
    job_id = sent.output.split("Job ", 1)[1].split(":", 1)[0]
    dncq("restore-replaced", job_id)

    restores = dncq("jobs", "--kind", "restore")
    sends = dncq("jobs", "--kind", "send")

    assert restores.exit_code == 0, restores.output
    assert [(row["kind"], row["id"] == job_id) for row in table_rows(restores.output)] == [
        ("restore", False)]
    assert [(row["kind"], row["id"]) for row in table_rows(sends.output)] == [("send", job_id)]


def test_jobs_prune_removes_finished_jobs(live_with_worker, program):
    dncq("send", str(program), "--to", "m0", "--wait")
    assert dncq("jobs").output.count("send") == 1
    result = dncq("jobs", "prune", "--older-than-days", "0")
    assert "Pruned 1 jobs" in result.output
    assert "send" not in dncq("jobs").output


@pytest.mark.parametrize("days", ["-1", "999999999"])
def test_jobs_prune_refuses_an_age_out_of_range_and_prunes_nothing(live_with_worker, program,
                                                                   days):
    assert dncq("send", str(program), "--to", "m0", "--wait").exit_code == 0
    result = dncq("jobs", "prune", "--older-than-days", days)
    assert result.exit_code == 2 and "older-than-days" in result.output
    assert dncq("jobs").output.count("send") == 1


def test_send_without_a_target_choice_is_a_usage_error(live_with_worker, program):
    result = dncq("send", str(program))
    assert result.exit_code == 2


def test_a_page_of_some_targets_says_what_it_is_a_page_of(
        live_with_worker, queue_settings, program):
    on_machine(queue_settings, "m1", "P.nc").write_text("old")  # 142 there: one fails
    sent = dncq("send", str(program), "--all", "--wait")
    job_id = sent.output.split("Job ", 1)[1].split(":", 1)[0]

    whole = dncq("job", job_id, "--limit", "1").output
    chosen = dncq("job", job_id, "--limit", "1", "--state", "succeeded").output

    assert "Showing 1 of 3 targets; the next ones: " in whole
    assert "Showing 1 of the matching targets; the next ones: " in " ".join(chosen.split())
    assert "--state succeeded --after" in " ".join(chosen.split())


def test_a_page_without_the_failed_targets_says_how_to_list_them(
        live_with_worker, queue_settings, program):
    # A rollout to 200 machines ended on its first 100 targets, all succeeded, and `1 failed`.
    on_machine(queue_settings, "m2", "P.nc").write_text("old")  # 142 there: the last fails
    sent = dncq("send", str(program), "--all", "--wait")
    job_id = sent.output.split("Job ", 1)[1].split(":", 1)[0]

    page = dncq("job", job_id, "--limit", "1", width=200).output
    hint = f"1 failed target not in this page: dncq job {job_id} --limit 1 --state failed"
    listed = dncq("job", job_id, "--limit", "1", "--state", "failed", width=200)

    assert hint in page
    assert [row["machine"] for row in table_rows(listed.output) if row["#"].isdigit()] == ["m2"]


def test_ctrl_c_before_dncq_answers_a_send_says_the_job_may_be_queued(
        live_with_worker, program, monkeypatch):
    # The job was recorded and went on to every machine; the command ended on a bare ^C.
    call = Client.call

    def interrupted(self, method, path, **kwargs):  # Ctrl-C once dncq has the request
        answer = call(self, method, path, **kwargs)
        if (method, path) == ("POST", "/api/jobs"):
            raise KeyboardInterrupt
        return answer

    monkeypatch.setattr(Client, "call", interrupted)
    result = dncq("send", str(program), "--to", "m0")
    monkeypatch.setattr(Client, "call", call)

    assert result.exit_code == 130
    assert "the job was queued all the same: dncq jobs shows it, and dncq cancel JOB" in \
        " ".join(result.output.split())
    assert dncq("jobs").output.count("P.nc") == 1


def test_ctrl_c_before_dncq_answers_a_retry_says_the_targets_may_be_retried(
        live_with_worker, queue_settings, program, ctrl_c_before_the_answer):
    # The targets were queued again; the command ended on a bare ^C, or printed nothing.
    on_machine(queue_settings, "m1", "P.nc").write_text("old")  # 142 there: failed
    sent = dncq("send", str(program), "--to", "m0,m1")
    job_id = sent.output.split("Job ", 1)[1].split(":", 1)[0]
    ctrl_c_before_the_answer("/retry")

    result = dncq("retry", job_id)

    assert result.exit_code == 130
    assert (f"Stopped before dncq answered. If it had the whole request, the failed and "
            f"cancelled targets of job {job_id} were queued again all the same: dncq job "
            f"{job_id} shows them") in " ".join(result.output.split())
    wait_until(lambda: [row["tries"] for row in table_rows(dncq("job", job_id).output)
                        if row["#"].isdigit()] == ["1", "2"], timeout_s=20)


def test_ctrl_c_before_dncq_answers_restore_replaced_says_the_restore_may_be_queued(
        live_with_worker, queue_settings, program, ctrl_c_before_the_answer):
    on_machine(queue_settings, "m0", "P.nc").write_text("old\n")
    sent = dncq("send", str(program), "--to", "m0", "--replace")
    job_id = sent.output.split("Job ", 1)[1].split(":", 1)[0]
    ctrl_c_before_the_answer("/restore-replaced")

    result = dncq("restore-replaced", job_id)

    assert result.exit_code == 130
    assert ("Stopped before dncq answered. If it had the whole request, the restore job was "
            "queued all the same: dncq jobs --kind restore shows it, and dncq cancel JOB") \
        in " ".join(result.output.split())
    assert [row["kind"] for row in table_rows(dncq("jobs", "--kind", "restore").output)] == [
        "restore"]


def test_ctrl_c_before_dncq_answers_a_cancel_says_the_targets_may_be_cancelled(
        live_with_worker, queue_settings, program, ctrl_c_before_the_answer):
    options = queue_settings.data_dir / "mock" / "m1" / "options.json"
    options.parent.mkdir(parents=True, exist_ok=True)
    options.write_text('{"offline": true}')  # waits there until cancelled
    sent = dncq("send", str(program), "--to", "m1", "--deliver-within", "1h", "--no-wait")
    job_id = sent.output.split("Job ", 1)[1].split(":", 1)[0]
    ctrl_c_before_the_answer("/cancel")

    result = dncq("cancel", job_id)

    assert result.exit_code == 130
    assert (f"Stopped before dncq answered. If it had the whole request, the targets of job "
            f"{job_id} not started were cancelled all the same: dncq job {job_id} shows them.") \
        in " ".join(result.output.split())
    wait_until(lambda: [row["state"] for row in table_rows(dncq("jobs").output)] == [
        "cancelled"], timeout_s=20)
