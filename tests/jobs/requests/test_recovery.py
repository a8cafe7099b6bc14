"""A request whose worker died before it answered ends failed, once, through the reaper."""

from __future__ import annotations

from datetime import timedelta

from sqlalchemy import update

from jobs.db import session_scope
from jobs.models import Target, utcnow
from jobs.requests import record
from tests.jobs.helpers import wait_done


def test_a_request_left_running_by_a_dead_worker_fails_saying_so_and_is_not_answered_twice(
        queue_settings, queue_client, add_machines) -> None:
    add_machines({"id": "2002", "name": "RS232-J", "model": "Fanuc 0i-F", "transport": "serial",
                  "options": {"url": "socket://127.0.0.1:9"}, "requests": {"enabled": True}})
    opened = record.open_job(settings=queue_settings, machine_id="2002", file_name="O8888",
                             received=b"%\nO8888\n(PRG=0010)\n%\n", created_by="machine:2002",
                             steps=[{"action": "send", "folder": "", "fileName": "0010"}])
    with session_scope(queue_settings.resolved_database_url) as session:  # its worker died
        session.execute(update(Target).where(Target.job_id == opened.job_id)
                        .values(lease_until=utcnow() - timedelta(minutes=5)))

    job = wait_done(queue_client, opened.job_id)

    [target] = job["targets"]
    assert job["state"] == "failed" and target["state"] == "failed"
    assert target["statusMsg"] == record.LISTENER_LOST
    assert target["attempts"] == 2 and target["history"][0]["errorMsg"]  # the lost one kept
    retry = queue_client.post(f"/api/jobs/{opened.job_id}/retry")
    assert retry.status_code in (400, 409) and "asked again from the control" in retry.text
