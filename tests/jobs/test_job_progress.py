"""A job's progress in bytes and its next retry, as the API and the CLI's bar show them."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

import pytest

from jobs.cli.common import err
from tests.jobs.cli.runner import dncq
from tests.jobs.helpers import on_machine, wait_done, wait_until

SIZE = 3 * 1024 * 1024  # over the 1 MiB from which a transfer reports its bytes
PROGRAM = ("G1 X1 Y1\n" * (SIZE // 9 + 1))[:SIZE]


@pytest.fixture
def queue_settings(queue_settings):
    """Retries a long while apart: a next try due within the 0.1-0.5 s the other tests use
    could be past already when a loaded host answers the request that shows it."""
    return queue_settings.model_copy(update={"retry_base_s": 30.0, "retry_max_s": 60.0})


def slow_machines(add_machines, n: int) -> None:
    add_machines(*[{"id": f"s{i}", "name": f"S{i}", "model": "Mock",
                    "options": {"bytes_per_s": 1024 * 1024}} for i in range(n)])


def test_a_send_job_reports_bytes_delivered_before_any_target_finishes(
        queue_client, add_machines):
    slow_machines(add_machines, 2)
    job_id = queue_client.post("/api/jobs", json={
        "kind": "send", "content": PROGRAM,
        "targets": [{"machineID": f"s{i}", "fileName": "BIG.nc"} for i in range(2)]}).json()["id"]

    def moving() -> bool:
        summary = queue_client.get(f"/api/jobs/{job_id}", params={"limit": 0}).json()
        return summary["bytes"]["done"] > 0 and summary["counts"]["succeeded"] == 0

    wait_until(moving)
    done = wait_done(queue_client, job_id)
    assert done["bytes"] == {"done": 2 * SIZE, "total": 2 * SIZE}


def test_a_failed_target_leaves_the_bytes_still_to_deliver(queue_client, add_machines):
    slow_machines(add_machines, 1)
    job_id = queue_client.post("/api/jobs", json={
        "kind": "send", "content": PROGRAM,
        "targets": [{"machineID": "s0", "fileName": "BIG.nc"},
                    {"machineID": "nowhere", "fileName": "BIG.nc"}]}).json()["id"]

    done = wait_done(queue_client, job_id)

    assert done["bytes"] == {"done": SIZE, "total": SIZE}


def test_a_target_waiting_to_retry_says_when_its_next_try_is_due(queue_client, add_machines):
    add_machines({"id": "off", "name": "Off", "model": "Mock", "options": {"offline": True}})
    job_id = queue_client.post("/api/jobs", json={
        "kind": "send", "content": "G0 X0\n", "deliver_within": "1h",
        "targets": [{"machineID": "off", "fileName": "P.nc"}]}).json()["id"]

    def waiting() -> bool:
        summary = queue_client.get(f"/api/jobs/{job_id}", params={"limit": 0}).json()
        return summary["nextAttemptAt"] is not None and summary["counts"]["running"] == 0

    wait_until(waiting)
    due = queue_client.get(f"/api/jobs/{job_id}", params={"limit": 0}).json()["nextAttemptAt"]
    assert datetime.fromisoformat(due) > datetime.now(UTC)
    queue_client.post(f"/api/jobs/{job_id}/cancel")


def test_dncq_send_wait_shows_the_bytes_of_the_transfer(live_with_worker, queue_settings,
                                                         tmp_path, monkeypatch):
    # The whole bar on one line. The console's width, not COLUMNS: a console made where
    # COLUMNS was set at import (as pytest-xdist's workers have it) keeps that width.
    monkeypatch.setattr(err, "width", 200)
    monkeypatch.setattr(err, "_force_terminal", True)  # piped, the bar is left out
    program = tmp_path / "BIG.nc"
    program.write_text(PROGRAM)

    sent = dncq("send", str(program), "--to", "m0,m1", "--wait")

    assert sent.exit_code == 0, sent.output
    assert "6.3/6.3 MB" in sent.output  # Rich's decimal megabytes of 2 x 3 MiB
    assert on_machine(queue_settings, "m1", "BIG.nc").stat().st_size == SIZE


def test_the_bar_says_retrying_in_while_every_target_left_waits_for_its_time():
    from datetime import timedelta

    from jobs.cli.job_follow import _retry_note

    due = (datetime.now(UTC) + timedelta(seconds=23.5)).isoformat()
    waiting = {"counts": {"running": 0}, "nextAttemptAt": due}
    busy = {"counts": {"running": 1}, "nextAttemptAt": due}

    assert _retry_note(waiting) in (" · retrying in 24 s", " · retrying in 23 s")
    assert _retry_note(busy) == ""


def test_the_bar_counts_failed_and_cancelled_targets_apart_and_leaves_out_zeros():
    from jobs.cli.job_follow import _tally

    def job(**counts: int) -> dict[str, Any]:
        full = {"pending": 0, "running": 0, "succeeded": 0, "skipped": 0, "failed": 0,
                "cancelled": 0} | counts
        return {"counts": full, "total": sum(full.values()), "nextAttemptAt": None}

    assert _tally(job(failed=7, cancelled=2)) == (
        "9/9 done · [red]7 failed[/red] · [yellow]2 cancelled[/yellow]")
    assert _tally(job(succeeded=3, running=2, pending=4)) == "3/9 done · 2 running"
    assert _tally(job(succeeded=9)) == "9/9 done"
